"""The spec §3 scan folder: round trip, lazy frames, and every validation error naming its file and line."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.inputs.scan import Scan, in_memory_loader
from services.store.scan_folder import ScanFormatError, read_scan_folder, write_scan_folder

W, H = 48, 32


def small_scan(dtype: type = np.uint8, n: int = 3) -> Scan:
    """A tiny in-memory scan with every optional part present."""
    rng = np.random.default_rng(0)
    top = np.iinfo(dtype).max
    frames = [rng.integers(0, top, (H, W), dtype=dtype, endpoint=True) for _ in range(n)]
    mask = np.zeros((H, W), np.uint8)
    mask[4:-4, 4:-4] = 255
    ref = np.array([[0.0, 0.0], [np.nan, np.nan], [2.5, -1.0 / 3.0]])[:n]
    return Scan(
        calibration=default_calibration(W, H, dist_coeffs=(-0.1, 0.01, 0.0, 0.0, 0.0), young_modulus_kpa=15.2),
        frame_seq=np.arange(n),
        frame_t_s=0.1 * np.arange(n) + 1.0 / 3.0,
        force_t_s=np.linspace(0.0, 1.0, 11),
        forces_n=rng.uniform(0, 3, (11, 4)),
        frame_loader=in_memory_loader(frames),
        mask=mask,
        imu_t_s=np.linspace(0.0, 1.0, 5),
        imu_tilt_deg=rng.normal(0, 0.1, (5, 2)),
        reference_mm=ref,
        truth={"poses": np.zeros((n, 3)), "young_modulus_kpa": np.float64(16.0), "blurred": [np.int64(1)]},
    )


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    write_scan_folder(small_scan(), tmp_path / "scan")
    return tmp_path / "scan"


@pytest.mark.parametrize(("dtype", "ext"), [(np.uint8, "png"), (np.uint16, "png"), (np.uint16, "tif")])
def test_round_trip(tmp_path: Path, dtype: type, ext: str) -> None:
    scan = small_scan(dtype)
    write_scan_folder(scan, tmp_path / "s", frame_ext=ext)
    back = read_scan_folder(tmp_path / "s")
    assert back.calibration == scan.calibration
    # floats are written with repr(): they read back bit-exact
    for name in ("frame_seq", "frame_t_s", "force_t_s", "forces_n", "imu_t_s", "imu_tilt_deg", "mask"):
        np.testing.assert_array_equal(getattr(back, name), getattr(scan, name), err_msg=name)
    np.testing.assert_array_equal(back.reference_mm, scan.reference_mm)  # NaN rows stay NaN
    for k in range(len(scan)):
        f = back.frame(k)
        assert f.dtype == dtype
        np.testing.assert_array_equal(f, scan.frame(k))
    assert back.truth == {"poses": [[0.0] * 3] * 3, "young_modulus_kpa": 16.0, "blurred": [1]}


def test_a_dropped_frame_leaves_a_gap_in_seq_and_the_reference_is_spread_by_seq(folder: Path) -> None:
    # spec §3: a frame the camera dropped leaves a gap in seq; the path's rows run over every seq (it is missing)
    (folder / "frames.csv").write_text("seq,t_s\n0,0.1\n2,0.3\n")
    (folder / "reference.csv").write_text("seq,x_mm,y_mm\n0,0,0\n2,4.5,1\n")
    (folder / "frames" / "000001.png").unlink()
    scan = read_scan_folder(folder)
    np.testing.assert_array_equal(scan.frame_seq, [0, 2])
    assert len(scan) == 2 and scan.n_seqs == 3
    assert scan.frame(1).shape == (H, W)  # position 1 is seq 2
    rows = scan.by_seq(scan.reference_mm)
    assert rows.shape == (3, 2) and np.isnan(rows[1]).all() and rows[2].tolist() == [4.5, 1.0]


def test_optional_files_may_be_absent(folder: Path) -> None:
    for name in ("imu.csv", "mask.png", "reference.csv", "truth.json"):
        (folder / name).unlink()
    scan = read_scan_folder(folder)
    assert scan.mask is None and scan.imu_t_s is None and scan.reference_mm is None and scan.truth == {}


def test_frames_are_sorted_by_seq_and_loaded_lazily(folder: Path) -> None:
    (folder / "frames.csv").write_text("seq,t_s\n2,0.5\n0,0.1\n1,0.3\n")
    (folder / "frames" / "000002.png").unlink()
    cv2.imwrite(str(folder / "frames" / "000002.tiff"), np.full((H, W), 7, np.uint8))
    scan = read_scan_folder(folder)
    np.testing.assert_array_equal(scan.frame_t_s, [0.1, 0.3, 0.5])
    assert scan.frame(2)[0, 0] == 7
    (folder / "frames" / "000001.png").write_bytes(b"not an image")  # broken only when loaded
    with pytest.raises(ScanFormatError) as e:
        scan.frame(1)
    assert e.value.file == "frames/000001.png" and "cannot be read" in str(e.value)


def test_write_refuses_a_non_empty_folder_unless_overwrite(folder: Path) -> None:
    with pytest.raises(FileExistsError):
        write_scan_folder(small_scan(), folder)
    cv2.imwrite(str(folder / "frames" / "000000.tif"), np.zeros((H, W), np.uint8))
    (folder / "notes.txt").write_text("keep me")
    write_scan_folder(small_scan(np.uint16), folder, overwrite=True)
    assert (folder / "notes.txt").read_text() == "keep me"  # only scan files are removed
    assert read_scan_folder(folder).frame(0).dtype == np.uint16  # the stale .tif is gone: no ambiguity


def expect_error(folder: Path, file: str, line: int | None, fragment: str) -> ScanFormatError:
    with pytest.raises(ScanFormatError) as e:
        read_scan_folder(folder)
    err = e.value
    assert err.file == file, str(err)
    assert err.line == line, str(err)
    assert fragment in err.message, str(err)
    assert str(err).startswith(f"{file} line {line}: " if line is not None else f"{file}: ")
    return err


def test_forces_row_with_missing_number(folder: Path) -> None:
    lines = (folder / "forces.csv").read_text().splitlines()
    lines[11] = ",".join(lines[11].split(",")[:4])  # line 12 of the file
    (folder / "forces.csv").write_text("\n".join(lines) + "\n")
    err = expect_error(folder, "forces.csv", 12, "expected 5 numbers")
    assert str(err) == "forces.csv line 12: expected 5 numbers (t_s,f1_n,f2_n,f3_n,f4_n), got 4"


@pytest.mark.parametrize(
    ("file", "text", "line", "fragment"),
    [
        ("frames.csv", "seq,time\n0,0.1\n", 1, "expected the header seq,t_s"),
        ("frames.csv", "seq,t_s\n0,0.1\nx,0.2\n", 3, "seq must be a whole number"),
        ("frames.csv", "seq,t_s\n0,0.1\n1,nan\n", 3, "t_s must be finite"),
        ("frames.csv", "seq,t_s\n0,0.1\n1,0.2\n0,0.3\n", 4, "seq 0 repeats line 2"),
        ("frames.csv", "seq,t_s\n0,0.1\n1,0.2\n2,0.3\n3,0.4\n", 5, "no frame file frames/000003.png"),
        ("frames.csv", "seq,t_s\n", None, "no frames listed"),
        ("forces.csv", "t_s,f1_n,f2_n,f3_n,f4_n\n0,1,1,1,1\n", None, "at least 2 samples"),
        ("forces.csv", "t_s,f1_n,f2_n,f3_n,f4_n\n0,1,1,1,1\n0.1,1,inf,1,1\n", 3, "f2_n must be finite"),
        ("forces.csv", "t_s,f1,f2,f3,f4\n0,1,1,1,1\n0.1,1,1,1,1\n", 1, "expected the header"),
        ("imu.csv", "t_s,tilt_x_deg,tilt_y_deg\n0,0.1,0.2\n0.1,0.1,abc\n", 3, "tilt_y_deg must be a number"),
        ("reference.csv", "seq,x_mm,y_mm\n0,0,0\n9,1,1\n", 3, "seq 9 is not a frame"),
        ("reference.csv", "seq,x_mm,y_mm\n0,0,0\n0,1,1\n", 3, "seq 0 repeats line 2"),
        ("calibration.json", '{\n  "image_size": [48, 32],\n  oops\n}', 3, "malformed JSON"),
        ("calibration.json", '{"image_size": [48, 32], "px_per_mm": 8, "colour": 1}', None, "unknown field"),
        ("truth.json", "[1, 2]", 1, "expected a JSON object"),
    ],
)  # fmt: skip
def test_validation_errors_name_file_and_line(
    folder: Path, file: str, text: str, line: int | None, fragment: str
) -> None:
    (folder / file).write_text(text)
    expect_error(folder, file, line, fragment)


@pytest.mark.parametrize("name", ["calibration.json", "frames.csv", "forces.csv"])
def test_missing_required_file(folder: Path, name: str) -> None:
    (folder / name).unlink()
    expect_error(folder, name, None, "missing")


def test_missing_frames_folder_and_ambiguous_frame_files(folder: Path) -> None:
    cv2.imwrite(str(folder / "frames" / "000001.tif"), np.zeros((H, W), np.uint8))
    expect_error(folder, "frames.csv", 3, "ambiguous frame files frames/000001.png, frames/000001.tif")
    for p in (folder / "frames").iterdir():
        p.unlink()
    (folder / "frames").rmdir()
    expect_error(folder, "frames/", None, "missing")


def test_frame_checks_on_load(folder: Path) -> None:
    cv2.imwrite(str(folder / "frames" / "000001.png"), np.zeros((H, W, 3), np.uint8))
    cv2.imwrite(str(folder / "frames" / "000002.png"), np.zeros((H + 1, W), np.uint8))
    scan = read_scan_folder(folder)
    scan.frame(0)
    with pytest.raises(ScanFormatError, match=r"^frames/000001\.png: colour image"):
        scan.frame(1)
    with pytest.raises(ScanFormatError, match=r"^frames/000002\.png: image is 48x33 px; calibration .* 48x32"):
        scan.frame(2)


def test_mask_must_match_the_image_size(folder: Path) -> None:
    cv2.imwrite(str(folder / "mask.png"), np.zeros((H, W + 2), np.uint8))
    expect_error(folder, "mask.png", None, "image is 50x32 px")


def test_sixteen_bit_mask_is_thresholded_to_0_255(folder: Path) -> None:
    m = np.zeros((H, W), np.uint16)
    m[:, : W // 2] = 65535
    cv2.imwrite(str(folder / "mask.png"), m)
    mask = read_scan_folder(folder).mask
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255} and mask[0, 0] == 255


def test_errors_do_not_leak_the_folder_path(tmp_path: Path) -> None:
    missing = tmp_path / "Jane Doe 1970-01-01"
    with pytest.raises(ScanFormatError) as e:
        read_scan_folder(missing)
    assert "Jane" not in str(e.value)
    write_scan_folder(small_scan(), missing)
    (missing / "forces.csv").unlink()
    with pytest.raises(ScanFormatError) as e:
        read_scan_folder(missing)
    assert "Jane" not in str(e.value) and e.value.file == "forces.csv"


def test_truth_json_round_trips_numpy_values(folder: Path) -> None:
    doc = json.loads((folder / "truth.json").read_text())
    assert doc["young_modulus_kpa"] == 16.0 and doc["blurred"] == [1]
