"""Reading and writing the scan folder of spec §3 (calibration.json, frames.csv, frames/, forces.csv, ...)."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.core.inputs.calibration import Calibration, CalibrationError, parse_calibration
from services.core.inputs.reference import ReferenceFormatError, parse_reference_csv, reference_csv
from services.core.inputs.scan import Scan

FRAME_EXTENSIONS = ("png", "tif", "tiff")
FRAMES_HEADER = ("seq", "t_s")
FORCES_HEADER = ("t_s", "f1_n", "f2_n", "f3_n", "f4_n")
IMU_HEADER = ("t_s", "tilt_x_deg", "tilt_y_deg")
SCAN_FILES = (
    "calibration.json",
    "frames.csv",
    "forces.csv",
    "imu.csv",
    "mask.png",
    "reference.csv",
    "truth.json",
)


class ScanFormatError(ValueError):
    """A scan folder that does not follow spec §3; names the file (relative to the folder) and the line."""

    def __init__(self, file: str, line: int | None, message: str) -> None:
        self.file = file
        self.line = line
        self.message = message
        where = f"{file} line {line}" if line is not None else file
        super().__init__(f"{where}: {message}")


def frame_name(seq: int, ext: str = "png") -> str:
    """Return the relative file name of a frame, e.g. frames/000012.png (seq zero-padded to 6 digits)."""
    return f"frames/{seq:06d}.{ext}"


# --- reading -----------------------------------------------------------------------------------------------


def _read_text(folder: Path, name: str) -> str:
    try:
        data = (folder / name).read_bytes()
    except FileNotFoundError:
        raise ScanFormatError(name, None, "missing (required by the scan folder format)") from None
    except OSError as e:
        raise ScanFormatError(name, None, f"cannot be read ({e.strerror or type(e).__name__})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise ScanFormatError(name, line, "not valid UTF-8 text") from None


def _read_csv(
    folder: Path, name: str, header: tuple[str, ...], integer_columns: tuple[int, ...] = ()
) -> list[tuple[int, list[float]]]:
    """Return (line number, values) for every data row of a numeric CSV with exactly `header`."""
    lines = _read_text(folder, name).splitlines()
    if not lines or not lines[0].strip():
        raise ScanFormatError(name, 1, f"expected the header {','.join(header)}, got an empty line")
    got = tuple(c.strip() for c in lines[0].split(","))
    if got != header:
        raise ScanFormatError(name, 1, f"expected the header {','.join(header)}, got {lines[0].strip()[:80]!r}")
    rows: list[tuple[int, list[float]]] = []
    want = f"expected {len(header)} numbers ({','.join(header)})"
    for lineno, text in enumerate(lines[1:], start=2):
        if not text.strip():
            continue
        cells = [c.strip() for c in text.split(",")]
        if len(cells) != len(header):
            raise ScanFormatError(name, lineno, f"{want}, got {len(cells)}")
        values: list[float] = []
        for col, cell in enumerate(cells):
            if col in integer_columns:
                try:
                    values.append(int(cell))
                except ValueError:
                    raise ScanFormatError(
                        name, lineno, f"{header[col]} must be a whole number, got {cell[:30]!r}"
                    ) from None
                continue
            try:
                v = float(cell)
            except ValueError:
                raise ScanFormatError(name, lineno, f"{header[col]} must be a number, got {cell[:30]!r}") from None
            if not math.isfinite(v):
                raise ScanFormatError(name, lineno, f"{header[col]} must be finite, got {cell[:30]!r}")
            values.append(v)
        rows.append((lineno, values))
    return rows


def _read_json(folder: Path, name: str) -> Any:
    text = _read_text(folder, name)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise ScanFormatError(name, e.lineno, f"malformed JSON: {e.msg} (column {e.colno})") from None


def _read_calibration(folder: Path) -> Calibration:
    doc = _read_json(folder, "calibration.json")
    try:
        return parse_calibration(doc)
    except CalibrationError as e:
        raise ScanFormatError("calibration.json", None, str(e)) from None


def _read_frame_table(folder: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Return (seq (N,), t_s (N,), frame file names) sorted by seq, validated against frames/."""
    rows = _read_csv(folder, "frames.csv", FRAMES_HEADER, integer_columns=(0,))
    if not rows:
        raise ScanFormatError("frames.csv", None, "no frames listed")
    seen: dict[int, int] = {}
    for lineno, (seq, _) in rows:
        if seq < 0:
            raise ScanFormatError("frames.csv", lineno, f"seq must be >= 0, got {seq}")
        if seq in seen:
            raise ScanFormatError("frames.csv", lineno, f"seq {seq} repeats line {seen[seq]}")
        seen[int(seq)] = lineno
    rows.sort(key=lambda r: r[1][0])  # a seq the camera dropped leaves a gap (spec §3): that frame is `missing`
    try:
        present = set(os.listdir(folder / "frames"))
    except FileNotFoundError:
        raise ScanFormatError("frames/", None, "missing: the frame images folder is required") from None
    except NotADirectoryError:
        raise ScanFormatError("frames/", None, "expected a folder of frame images") from None
    names: list[str] = []
    for lineno, (seq, _) in rows:
        candidates = [f"{int(seq):06d}.{ext}" for ext in FRAME_EXTENSIONS]
        found = [c for c in candidates if c in present]
        if not found:
            raise ScanFormatError(
                "frames.csv", lineno, f"seq {int(seq)}: no frame file {frame_name(int(seq))} (or .tif/.tiff)"
            )
        if len(found) > 1:
            raise ScanFormatError(
                "frames.csv",
                lineno,
                f"seq {int(seq)}: ambiguous frame files {', '.join('frames/' + f for f in found)}",
            )
        names.append("frames/" + found[0])
    seq_arr = np.array([int(r[1][0]) for r in rows], dtype=np.int64)
    t_arr = np.array([float(r[1][1]) for r in rows], dtype=np.float64)
    return seq_arr, t_arr, names


def _read_stream(folder: Path, name: str, header: tuple[str, ...], min_rows: int) -> tuple[np.ndarray, np.ndarray]:
    rows = _read_csv(folder, name, header)
    if len(rows) < min_rows:
        raise ScanFormatError(name, None, f"expected at least {min_rows} samples, got {len(rows)}")
    data = np.array([r[1] for r in rows], dtype=np.float64).reshape(len(rows), len(header))
    return data[:, 0].copy(), data[:, 1:].copy()


def _read_reference(folder: Path, seq: np.ndarray) -> np.ndarray:
    """Return the reference track (N, 5) of the folder's reference.csv (services.core.inputs.reference)."""
    try:
        return parse_reference_csv(_read_text(folder, "reference.csv"), [int(s) for s in seq])
    except ReferenceFormatError as e:
        raise ScanFormatError("reference.csv", e.line, e.message) from None


def _check_image(img: np.ndarray | None, name: str, size: tuple[int, int], what: str) -> np.ndarray:
    if img is None:
        raise ScanFormatError(name, None, f"cannot be read as an image (expected 8- or 16-bit grayscale {what})")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise ScanFormatError(name, None, f"colour image ({img.shape[2]} channels); expected 8- or 16-bit grayscale")
    if img.dtype not in (np.uint8, np.uint16):
        raise ScanFormatError(name, None, f"pixel type {img.dtype}; expected 8- or 16-bit grayscale")
    w, h = size
    if img.shape != (h, w):
        raise ScanFormatError(
            name, None, f"image is {img.shape[1]}x{img.shape[0]} px; calibration image_size is {w}x{h}"
        )
    return img


def _read_mask(folder: Path, size: tuple[int, int]) -> np.ndarray:
    img = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_UNCHANGED)
    img = _check_image(img, "mask.png", size, "mask")
    half = np.iinfo(img.dtype).max // 2
    return np.where(img > half, 255, 0).astype(np.uint8)


def frame_file_loader(
    folder: str | os.PathLike[str], names: list[str], size: tuple[int, int]
) -> Callable[[int], np.ndarray]:
    """Return a frame_loader reading frames lazily (names relative to folder); errors name the frame file."""
    root = Path(folder)

    def load(index: int) -> np.ndarray:
        name = names[index]
        img = cv2.imread(str(root / name), cv2.IMREAD_UNCHANGED)
        return _check_image(img, name, size, "frame")

    return load


def read_scan_folder(path: str | os.PathLike[str]) -> Scan:
    """Return the Scan in a spec §3 scan folder (frames loaded lazily); raise ScanFormatError if invalid."""
    folder = Path(path)
    if not folder.is_dir():
        raise ScanFormatError("(scan folder)", None, "not found or not a folder")
    calib = _read_calibration(folder)
    seq, t_s, names = _read_frame_table(folder)
    force_t, forces = _read_stream(folder, "forces.csv", FORCES_HEADER, 2)
    imu_t = imu = None
    if (folder / "imu.csv").exists():
        imu_t, imu = _read_stream(folder, "imu.csv", IMU_HEADER, 2)
    mask = _read_mask(folder, calib.image_size) if (folder / "mask.png").exists() else None
    track = _read_reference(folder, seq) if (folder / "reference.csv").exists() else None
    truth: dict[str, Any] = {}
    if (folder / "truth.json").exists():
        doc = _read_json(folder, "truth.json")
        if not isinstance(doc, dict):
            raise ScanFormatError("truth.json", 1, "expected a JSON object")
        truth = doc
    return Scan(
        calibration=calib,
        frame_seq=seq,
        frame_t_s=t_s,
        force_t_s=force_t,
        forces_n=forces,
        frame_loader=frame_file_loader(folder, names, calib.image_size),
        mask=mask,
        imu_t_s=imu_t,
        imu_tilt_deg=imu,
        reference_mm=None if track is None else track[:, :2].copy(),
        reference_angles_deg=None if track is None or np.isnan(track[:, 2:]).all() else track[:, 2:].copy(),
        truth=truth,
    )


# --- writing -----------------------------------------------------------------------------------------------


def _jsonable(value: Any) -> Any:
    """Return value with numpy scalars/arrays (and tuples) turned into plain JSON types."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    return value


def _num(v: float) -> str:
    return repr(float(v))  # shortest text that reads back to the same float64


def _write_csv(path: Path, header: tuple[str, ...], rows: list[list[str]]) -> None:
    lines = [",".join(header)] + [",".join(r) for r in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _remove_stale(folder: Path) -> None:
    """Remove the scan files a previous write may have left (only names this module writes)."""
    for name in SCAN_FILES:
        p = folder / name
        if p.is_file():
            p.unlink()
    frames = folder / "frames"
    if frames.is_dir():
        for p in frames.iterdir():
            stem, _, ext = p.name.partition(".")
            if p.is_file() and len(stem) == 6 and stem.isdigit() and ext in FRAME_EXTENSIONS:
                p.unlink()


def write_scan_folder(
    scan: Scan, path: str | os.PathLike[str], frame_ext: str = "png", overwrite: bool = False
) -> None:
    """Write a Scan as a spec §3 scan folder (plus reference.csv and truth.json when the scan has them).

    The folder must be new or empty unless overwrite=True, which first removes the scan files (and only
    those) that a previous write left there.
    """
    if frame_ext not in FRAME_EXTENSIONS:
        raise ValueError(f"frame_ext must be one of {', '.join(FRAME_EXTENSIONS)}, got {frame_ext!r}")
    folder = Path(path)
    if folder.exists() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError("scan folder exists and is not empty (pass overwrite=True to replace it)")
        _remove_stale(folder)
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    (folder / "calibration.json").write_text(json.dumps(scan.calibration.to_dict(), indent=2) + "\n", encoding="utf-8")
    seqs = [int(s) for s in scan.frame_seq]
    _write_csv(
        folder / "frames.csv",
        FRAMES_HEADER,
        [[str(s), _num(t)] for s, t in zip(seqs, scan.frame_t_s, strict=True)],
    )
    for index, seq in enumerate(seqs):
        img = np.asarray(scan.frame(index))
        if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"frame {seq}: expected a 2-D uint8 or uint16 array, got {img.dtype} {img.shape}")
        name = folder / frame_name(seq, frame_ext)
        if not cv2.imwrite(str(name), img):
            raise OSError(f"could not write {frame_name(seq, frame_ext)}")
    forces = np.asarray(scan.forces_n, dtype=np.float64).reshape(len(scan.force_t_s), 4)
    _write_csv(
        folder / "forces.csv",
        FORCES_HEADER,
        [[_num(t), *(_num(v) for v in row)] for t, row in zip(scan.force_t_s, forces, strict=True)],
    )
    if scan.imu_t_s is not None and scan.imu_tilt_deg is not None:
        imu = np.asarray(scan.imu_tilt_deg, dtype=np.float64).reshape(len(scan.imu_t_s), 2)
        _write_csv(
            folder / "imu.csv",
            IMU_HEADER,
            [[_num(t), _num(a), _num(b)] for t, (a, b) in zip(scan.imu_t_s, imu, strict=True)],
        )
    if scan.mask is not None:
        cv2.imwrite(str(folder / "mask.png"), np.where(np.asarray(scan.mask) > 0, 255, 0).astype(np.uint8))
    if scan.reference_mm is not None:
        track = np.asarray(scan.reference_mm, dtype=np.float64).reshape(len(seqs), 2)
        if scan.reference_angles_deg is not None:
            track = np.hstack([track, np.asarray(scan.reference_angles_deg, dtype=np.float64).reshape(len(seqs), 3)])
        (folder / "reference.csv").write_text(reference_csv(seqs, track), encoding="utf-8")
    if scan.truth:
        (folder / "truth.json").write_text(json.dumps(_jsonable(scan.truth), indent=1) + "\n", encoding="utf-8")
