"""The `veinmosaic` command line: simulate -> reconstruct -> outputs, bad input exits 2, calibrate."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from cli.main import main
from services.core.path_rows import PATH_COLUMNS
from tests.services.core.synthetic_veins import vessel_photo
from tests.tolerances import TOL

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "scan"
    assert main(["simulate", "--scenario", "short", "--seed", "1", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def outputs(scan_dir: Path) -> Path:
    out = scan_dir.parent / "out"
    assert main(["reconstruct", str(scan_dir), "--out", str(out), "--method", "best"]) == 0
    return out


def test_simulate_writes_a_scan_folder(scan_dir: Path) -> None:
    names = {p.name for p in scan_dir.iterdir()}
    assert {"calibration.json", "frames.csv", "frames", "forces.csv", "reference.csv"} <= names
    assert len(list((scan_dir / "frames").iterdir())) == 40


def test_simulate_takes_its_veins_from_a_photograph(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    photo, _ = vessel_photo()
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    out = tmp_path / "scan"
    assert main(["simulate", "--scenario", "short", "--texture", str(tmp_path / "photo.png"), "--out", str(out)]) == 0
    assert json.loads((out / "truth.json").read_text())["texture"] == "photograph"
    missing = tmp_path / "none.png"
    assert main(["simulate", "--texture", str(missing), "--out", str(tmp_path / "other")]) == 2
    assert f"--texture: cannot read an image from {missing}" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


def test_reconstruct_writes_the_path(outputs: Path) -> None:
    with (outputs / "path.csv").open() as f:
        table = list(csv.reader(f))
    assert tuple(table[0]) == PATH_COLUMNS  # spec §4 columns in order
    assert len(table) == 41  # header + 40 frames
    assert [row[0] for row in table[1:]] == [str(i) for i in range(40)]
    status = PATH_COLUMNS.index("status")
    assert all(row[status : status + 3] == ["ok", "", "0"] for row in table[1:])  # no reason, stroke 0 (one stroke)
    drag = PATH_COLUMNS.index("drag_x_mm")
    assert all(row[drag] != "" and row[drag + 1] != "" for row in table[1:])  # every placed frame: its drag (0 here)
    assert table[1][2:5] == ["0.0000", "0.0000", "0.0000"]  # frame 0 is the origin


def test_reconstruct_writes_the_mosaic(outputs: Path) -> None:
    png = cv2.imread(str(outputs / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert png is not None and png.dtype == np.uint8 and png.ndim == 2  # 8-bit grayscale
    meta = json.loads((outputs / "mosaic.json").read_text())
    assert meta["px_per_mm"] == 8.0
    assert (meta["width"], meta["height"]) == (png.shape[1], png.shape[0])
    ox, oy = meta["origin_px"]
    assert 0 <= ox < meta["width"] and 0 <= oy < meta["height"]
    force = cv2.imread(str(outputs / "force.png"), cv2.IMREAD_UNCHANGED)
    assert force is not None and force.shape == (*png.shape, 3)


def test_reconstruct_writes_the_report(outputs: Path) -> None:
    report = json.loads((outputs / "report.json").read_text())
    # same band as tests/services/core/test_pipeline.py (measured 0.016 mm): the folder round trip (PNG frames,
    # CSV forces written with repr) must not cost accuracy
    assert TOL.best_short_rmse_mm[0] <= report["rmse_mm"] <= TOL.best_short_rmse_mm[1]
    assert report["registered_fraction"] == 1.0
    # where the error lies: what one similarity about frame 0 leaves is at most the RMSE over |b| (the fit
    # includes the identity; 1 % covers |b|), and a well-registered 40-frame scan's scale and turn are small
    g = report["global_error"]
    assert 0 < g["after_similarity_mm"] <= 1.01 * report["rmse_mm"]
    assert abs(g["scale_pct"]) < 0.5 and abs(g["turn_deg"]) < 0.5
    for name in ("paths.png", "errors.png"):
        assert cv2.imread(str(outputs / name)) is not None


def test_reconstruct_prints_a_summary(scan_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["reconstruct", str(scan_dir), "--out", str(tmp_path), "--method", "sift-chain"]) == 0
    out = capsys.readouterr().out
    assert "40/40 frames registered" in out and "RMSE" in out
    lines = out.splitlines()
    where = next(i for i, line in enumerate(lines) if line.startswith("where the error lies: the path"))
    assert lines[where + 1].startswith("RMSE")  # before the RMSE line: that and the angles stay the last two


def test_malformed_forces_exit_2_naming_file_and_line(
    scan_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad"
    shutil.copytree(scan_dir, bad)
    lines = (bad / "forces.csv").read_text().splitlines()
    lines[4] = "0.1,2.0,oops,1.0,1.0"  # line 5 of the file
    (bad / "forces.csv").write_text("\n".join(lines) + "\n")
    assert main(["reconstruct", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "forces.csv line 5" in err and "f2_n" in err
    assert not (tmp_path / "o").exists()  # nothing half-written


def test_missing_scan_folder_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["reconstruct", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "veinmosaic: error:" in capsys.readouterr().err


def test_unknown_method_is_a_usage_error(scan_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["reconstruct", str(scan_dir), "--out", str(tmp_path), "--method", "magic"])
    assert exc.value.code == 2


def test_calibrate_fits_and_writes_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scan = tmp_path / "calib"
    assert main(["simulate", "--scenario", "calib", "--seed", "1", "--out", str(scan)]) == 0
    before = json.loads((scan / "calibration.json").read_text())
    truth = json.loads((scan / "truth.json").read_text())
    capsys.readouterr()
    assert main(["calibrate", str(scan)]) == 0
    out = capsys.readouterr().out
    assert "Young's modulus E:" in out and "residual RMS" in out and "Hooke constant kappa:" in out
    after = json.loads((scan / "calibration.json").read_text())  # default --out: SCAN/calibration.json
    assert after["young_modulus_kpa"] != before["young_modulus_kpa"]
    # measured 15.17 kPa against a true 15.45 (nominal 16.1): the fit must land nearer the truth
    true_e = truth["young_modulus_kpa"]
    assert abs(after["young_modulus_kpa"] - true_e) < abs(before["young_modulus_kpa"] - true_e)
    assert set(after) == set(before)  # still a spec §3 document, no extra fields


def test_console_entry_point_runs(scan_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "scan"
    proc = subprocess.run(
        [sys.executable, "-m", "cli.main", "simulate", "--scenario", "short", "--seed", "1", "--out", str(out)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "wrote 40 frames" in proc.stdout
    # a separate process writes byte-identical tables: the simulator is deterministic for the seed
    for name in ("frames.csv", "forces.csv", "reference.csv"):
        assert (out / name).read_bytes() == (scan_dir / name).read_bytes()
    usage = subprocess.run(
        [sys.executable, "-m", "cli.main", "reconstruct"], capture_output=True, text=True, timeout=60, check=False
    )
    assert usage.returncode == 2 and "--out" in usage.stderr


def test_every_option_has_help_and_shows_its_default() -> None:
    import argparse

    from cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        text = " ".join(p.format_help().split())
        for action in p._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"{name} {action.dest}: no help text"
            if action.option_strings and action.default not in (None, False, [], "", argparse.SUPPRESS):
                assert "(default" in (action.help or "") or f"(default: {action.default})" in text
            if action.option_strings and not action.required:
                # every optional option says what happens without it, in its own help line
                shown = " ".join(p._get_formatter()._expand_help(action).split())
                assert "default" in shown or "(0:" in shown, f"{name} {'/'.join(action.option_strings)}: {shown}"
    demo = sub.choices["demo"]
    assert demo.parse_args([]).hold is False  # never silently dependent on the terminal
    assert "stop at the end" in demo.format_help()


def test_export_writes_dicom_that_reads_back(outputs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from pydicom import dcmread
    from pydicom.pixels import apply_rescale

    from services.store.output_folder import read_results_mosaic
    from tests.services.core.outputs.test_dicom_export import dciodvfy

    out = tmp_path / "dicom"
    args = ["export", str(outputs), "--out", str(out), "--acquired", "2025-03-04T10:20:30", "--study-key", "s1"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "no patient identity given" in printed
    mosaic = read_results_mosaic(outputs)
    # the three layers and, since reconstruct wrote sheet.pdf, the one-page report
    assert sorted(f.name for f in out.iterdir()) == ["coverage.dcm", "force.dcm", "report.dcm", "vein.dcm"]
    ds = {f.stem: dcmread(f) for f in out.iterdir()}
    for name, d in ds.items():
        errors = [line for line in dciodvfy((out / f"{name}.dcm").read_bytes(), tmp_path, name) if line[:5] == "Error"]
        assert errors == [], (name, errors)
        assert d.StudyDate == "20250304" and d.AcquisitionDateTime == "20250304102030"
        assert d.TimezoneOffsetFromUTC == "+0000"  # --acquired without an offset is UTC
        assert str(d.PatientName) == "" and d.PatientID == ""  # nothing invented
    assert len({d.StudyInstanceUID for d in ds.values()}) == 1
    assert bytes(ds["report"].EncapsulatedDocument).startswith((outputs / "sheet.pdf").read_bytes()[:64])
    for layer in ("vein", "force", "coverage"):
        assert float(ds[layer].PixelSpacing[0]) == pytest.approx(1 / mosaic.px_per_mm, rel=1e-9)  # mm per pixel
    assert (ds["vein"].pixel_array == mosaic.vein).all()
    scanned = mosaic.coverage > 0
    newtons = apply_rescale(ds["force"].pixel_array, ds["force"])
    np.testing.assert_allclose(newtons[scanned], mosaic.force_n[scanned], atol=0.005 + 1e-6)  # 0.01 N steps
    # the integrator's study context, when given, is written as given; --layer exports only that object
    only = tmp_path / "one"
    named = ["--patient-name", "Doe^Jane", "--patient-id", "H-1", "--patient-birth-date", "1970-01-01"]
    named += ["--accession-number", "A-9", "--laterality", "L", "--referring-physician", "Who^Doc"]
    assert main(["export", str(outputs), "--out", str(only), "--layer", "force", *named]) == 0
    assert "no patient identity" not in capsys.readouterr().out
    assert sorted(f.name for f in only.iterdir()) == ["force.dcm"]
    d = dcmread(only / "force.dcm")
    assert (str(d.PatientName), d.PatientID, d.PatientBirthDate, d.PatientSex) == ("Doe^Jane", "H-1", "19700101", "")
    assert (d.AccessionNumber, d.Laterality, str(d.ReferringPhysicianName)) == ("A-9", "L", "Who^Doc")
    assert d.StudyInstanceUID != ds["force"].StudyInstanceUID  # patient data: a study of its own


def test_export_uids_come_from_the_scan_not_the_folder(outputs: Path, scan_dir: Path, tmp_path: Path) -> None:
    from pydicom import dcmread

    from services.core.outputs.dicom_export import scan_digest
    from services.store.scan_folder import read_scan_folder

    meta = json.loads((outputs / "mosaic.json").read_text())
    assert meta["scan_digest"] == scan_digest(read_scan_folder(scan_dir))  # reconstruct records the scan's digest

    def uids(results: Path, out: Path) -> dict[str, tuple[str, str, str]]:
        assert main(["export", str(results), "--out", str(out), "--layer", "vein", "--layer", "force"]) == 0
        return {
            f.stem: (d.StudyInstanceUID, d.SeriesInstanceUID, d.SOPInstanceUID)
            for f in out.iterdir()
            for d in [dcmread(f)]
        }

    first = uids(outputs, tmp_path / "a")
    moved = tmp_path / "elsewhere"
    shutil.copytree(outputs, moved, ignore=shutil.ignore_patterns("dicom"))
    assert uids(moved, tmp_path / "b") == first  # another folder, the same scan: the same UIDs
    other = tmp_path / "other-scan"  # another scan's results (its digest differs) in a folder of the same name
    shutil.copytree(outputs, other, ignore=shutil.ignore_patterns("dicom"))
    (other / "mosaic.json").write_text(json.dumps({**meta, "scan_digest": "0" * 64}))
    again = uids(other, tmp_path / "c")
    assert not {u for t in again.values() for u in t} & {u for t in first.values() for u in t}


def test_export_refuses_a_bad_study_field_without_echoing_it(
    outputs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = ["--patient-id", "SECRET-ID-42", "--patient-birth-date", "1970-13-45"]
    assert main(["export", str(outputs), "--out", str(tmp_path / "x"), *bad]) == 2
    captured = capsys.readouterr()
    assert "patient_birth_date" in captured.err  # names the field ...
    assert "1970-13-45" not in captured.err + captured.out and "SECRET" not in captured.err + captured.out  # ... only
    assert not (tmp_path / "x").exists()  # nothing written
    assert main(["export", str(outputs), "--out", str(tmp_path / "y"), "--laterality", "B"]) == 2
    assert "laterality" in capsys.readouterr().err


def test_export_of_a_non_results_folder_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(tmp_path)]) == 2
    assert "not a reconstruction output folder" in capsys.readouterr().err


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="reads /proc/<pid>/cmdline (Linux)")
def test_worker_command_becomes_a_worker_process(tmp_path: Path) -> None:
    # `veinmosaic worker` execs `python -m workers.main` (the cli package never imports workers): the same
    # process turns into a worker, which keeps running against the embedded or configured Redis until stopped
    env = {k: v for k, v in os.environ.items() if k != "REDIS_URL"}  # its own embedded Redis, in its data dir
    env["VEINMOSAIC_DATA_DIR"] = str(tmp_path / "data")
    proc = subprocess.Popen([sys.executable, "-m", "cli.main", "worker"], cwd=tmp_path, env=env)
    try:
        deadline = time.monotonic() + 30
        cmdline = b""
        while time.monotonic() < deadline and proc.poll() is None:
            cmdline = Path(f"/proc/{proc.pid}/cmdline").read_bytes()
            if b"workers.main" in cmdline:
                break
            time.sleep(0.1)
        assert b"workers.main" in cmdline and b"cli.main" not in cmdline
        time.sleep(1.0)
        assert proc.poll() is None, "the worker exited instead of serving"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
