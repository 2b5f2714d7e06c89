"""The offline commands, run in this process on folders (no service): simulate, reconstruct, export, calibrate."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

from cli import output


def cmd_simulate(args: argparse.Namespace) -> int:
    """Return the exit code 0 after writing a simulated scan folder (spec §3) with reference.csv."""
    from services.core.simulation.scenarios import simulate
    from services.store.scan_folder import write_scan_folder
    from services.store.texture_photo import read_texture_photo

    texture = None if args.texture is None else read_texture_photo(args.texture)
    scan = simulate(args.scenario, args.seed, tissue=args.tissue, frames=args.frames, imu=args.imu, texture=texture)
    write_scan_folder(scan, args.out)
    length = scan.truth.get("path_length_mm", float("nan"))
    print(f"wrote {len(scan)} frames ({args.scenario}, seed {args.seed}, path {length:.0f} mm) to {args.out}")
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    """Return the exit code 0 after reconstructing a scan folder and writing path, mosaic, layers, plots and report.

    The outputs are services.store.output_folder's.
    """
    from services.core.methods import method_options
    from services.core.outputs.dicom_export import scan_digest
    from services.core.outputs.session_report import build_session_report
    from services.core.pipeline import reconstruct
    from services.store.output_folder import write_reconstruction
    from services.store.scan_folder import read_scan_folder

    scan = read_scan_folder(args.scan)
    options = method_options(args.method).with_overrides(_parse_options(args.option))
    with output.bar(f"reconstruct ({args.method})", len(scan)) as bar:
        recon = reconstruct(scan, options, progress=output.sized(bar))
    reference = scan.by_seq(scan.reference_track)
    # the figures first (the same report, without its images), so they show before the plots and sheet are drawn
    report = build_session_report(recon.rows, reference, None, draw=False)
    f = report.frames
    counts = f"{f.n_lost} lost, {f.n_rejected - f.n_no_contact} rejected"
    if f.n_no_contact:  # a scan in strokes: the frames taken in the air are neither placed nor counted
        counts += f"; {f.n_no_contact} taken off the skin"
    print(
        f"{f.n_ok}/{f.n_on_skin} frames registered ({100 * f.registered_fraction:.1f} %; {counts}) in "
        f"{recon.seconds:.1f} s; outputs to {args.out}"
    )
    output.print_warnings(report.warnings)  # before the figures: the RMSE and angle lines stay the last two
    if report.accuracy is not None:  # the RMSE and angle lines come last: scripts read the last two
        output.print_global_error(report.doc.get("global_error"))
        print(report.accuracy.summary())
    if "angles" in report.doc:
        a = report.doc["angles"]
        print(
            ", ".join(
                f"{k.removesuffix('_rmse_deg')} RMS error {v:.2f} deg" for k, v in a.items() if k.endswith("_rmse_deg")
            ),
            flush=True,
        )
    sys.stdout.flush()
    write_reconstruction(
        recon, args.out, reference, scan_digest=scan_digest(scan), label=Path(args.scan).resolve().name
    )
    print(f"one-page report: {Path(args.out) / 'sheet.pdf'}")
    return 0


def _parse_options(pairs: list[str]) -> dict[str, object]:
    """Return method overrides from KEY=VALUE strings, validated (and converted) by the one options model."""
    from services.core.method_options import check_overrides

    out: dict[str, object] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--option {pair!r}: expected KEY=VALUE")
        out[key] = value
    try:
        return check_overrides(out, lax=True)
    except ValueError as exc:
        raise ValueError(f"--option: {exc}") from None


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Return the exit code 0 after fitting E and kappa from a calibration scan.

    It prints the fits and writes an updated calibration.json.
    """
    from services.core.calibration_fit import calibrate_scan, format_calibration_report
    from services.store.scan_folder import read_scan_folder

    scan = read_scan_folder(args.scan)
    result = calibrate_scan(scan)
    print(format_calibration_report(result))
    out = Path(args.out) if args.out else Path(args.scan) / "calibration.json"
    out.write_text(json.dumps(result.calibration.to_dict(), indent=2))
    print(f"wrote {out}")
    return 0


STUDY_OPTIONS = (  # `veinmosaic export` options -> services.core.inputs.study fields (spec §5 `study`)
    "patient_id",
    "patient_name",
    "patient_birth_date",
    "patient_sex",
    "accession_number",
    "laterality",
    "referring_physician",
    "study_description",
)


def _results_key(results: Path) -> tuple[str, str]:
    """Return (UID key, what it is) of a results folder: its scan's content digest, else its results' content."""
    import hashlib

    meta = json.loads((results / "mosaic.json").read_text())
    digest = meta.get("scan_digest")
    if isinstance(digest, str) and digest:
        return f"scan:{digest}", "the scan's content"
    h = hashlib.sha256(b"veinmosaic results v1\0")  # a folder written before scan digests: its own content
    for name in ("layers.npz", "mosaic.png", "path.csv", "mosaic.json"):
        if (results / name).is_file():
            h.update(name.encode() + b"\0" + (results / name).read_bytes())
    return f"results:{h.hexdigest()}", "the results' content (folder written before scan digests)"


def cmd_export(args: argparse.Namespace) -> int:
    """Return the exit code 0 after writing a reconstruct output folder's layers as DICOM files of one study.

    Its one-page report too, when it has one.
    """
    from datetime import UTC, datetime

    from services.core.inputs.study import parse_study
    from services.core.outputs.dicom_export import STUDY_OBJECTS, ExportInfo, export_study
    from services.store.output_folder import read_results_mosaic
    from services.store.session_export import software_version

    results = Path(args.results)
    study = parse_study({name: getattr(args, name) or None for name in STUDY_OPTIONS})  # names a bad field only
    mosaic = read_results_mosaic(results)
    acquired = datetime.fromisoformat(args.acquired) if args.acquired else None
    if acquired is not None and acquired.tzinfo is None:
        acquired = acquired.replace(tzinfo=UTC)
    meta = json.loads((results / "mosaic.json").read_text())
    key, source = (args.study_key, "--study-key") if args.study_key else _results_key(results)
    info = ExportInfo(
        key=key,
        study=study,
        acquired=acquired,
        exported=datetime.now(UTC),
        method=str(meta.get("method") or ""),
        software=software_version(),
    )
    wanted = list(dict.fromkeys(args.layer or STUDY_OBJECTS))
    sheet = results / "sheet.pdf"
    pdf = sheet.read_bytes() if "report" in wanted and sheet.is_file() else None
    if pdf is None and "report" in wanted:
        if args.layer:
            raise ValueError(f"{results}: no sheet.pdf, the one-page report, to export")
        wanted.remove("report")
    out = Path(args.out) if args.out else results / "dicom"
    out.mkdir(parents=True, exist_ok=True)
    for name, data in export_study(mosaic, info, pdf, only=wanted).items():
        target = out / f"{name}.dcm"
        target.write_bytes(data)
        print(f"wrote {target}")
    print(f"UIDs derived from {source}" + (" and the study context" if study is not None else ""))
    if study is None:
        print("no patient identity given (no study context): the patient and order attributes are present and empty")
    return 0


def add_commands(command: Callable[[str, str], argparse.ArgumentParser]) -> None:
    """Add simulate, reconstruct, export and calibrate to the parser (`command(name, help)` adds one)."""
    p = command("simulate", "write a simulated scan folder (spec §3) with reference.csv and truth.json")
    p.add_argument(
        "--scenario",
        default="short",
        choices=["raster", "revisit", "hard", "short", "calib", "exam", "strokes"],
        help="kind of scan (exam: a minutes-long examination, passes over one area)",
    )
    p.add_argument("--seed", type=int, default=1, help="random seed (same seed, same scan)")
    p.add_argument("--frames", type=int, default=None, help="an exam's frames (default 2400: 4 min at 10 frames/s)")
    p.add_argument(
        "--imu",
        action="store_true",
        help="write imu.csv, the probe's IMU tilts (default: none, as on the shared scans; calib always has one)",
    )
    p.add_argument(
        "--tissue",
        default=None,
        choices=["linear", "stiffening", "power", "toe"],
        help="a patient's tissue law with a hand's tilts (default: the calibration phantom)",
    )
    p.add_argument(
        "--texture",
        type=Path,
        default=None,
        metavar="PHOTO",
        help="veins from a photograph's dark vessels, e.g. a fundus photograph (default: the procedural network)",
    )
    p.add_argument("--out", required=True, type=Path, help="scan folder to write (required)")
    p.set_defaults(func=cmd_simulate)

    p = command("reconstruct", "reconstruct a scan folder offline: path, mosaic, layers, plots, report")
    p.add_argument("scan", type=Path, help="scan folder (spec §3)")
    p.add_argument("--out", required=True, type=Path, help="output folder (required)")
    p.add_argument("--method", default="best", choices=["sift-chain", "paper", "best"], help="registration method")
    p.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a method option, repeatable, e.g. features=asift (full ASIFT) or refine=false (default: none)",
    )
    p.set_defaults(func=cmd_reconstruct)

    p = command("export", "write a reconstruct output folder's mosaic, force map and coverage as DICOM")
    p.add_argument("results", type=Path, help="a folder written by `veinmosaic reconstruct`")
    p.add_argument("--out", type=Path, default=None, help="folder for the .dcm files (default: RESULTS/dicom)")
    p.add_argument(
        "--layer", action="append", choices=["vein", "force", "coverage", "report"], help="object to export, "
        "repeatable (default: the three layers, and the report when RESULTS/sheet.pdf exists)"
    )  # fmt: skip
    p.add_argument(
        "--acquired", default=None, help="acquisition date-time, ISO 8601, UTC unless it has an offset (default: empty)"
    )
    p.add_argument(
        "--study-key",
        default=None,
        help="key the UIDs derive from (default: the digest of the scan's content that reconstruct recorded)",
    )
    study_help = {
        "patient_id": "PatientID",
        "patient_name": "PatientName, as 'Family^Given'",
        "patient_birth_date": "PatientBirthDate, YYYY-MM-DD",
        "patient_sex": "PatientSex: M, F or O",
        "accession_number": "AccessionNumber of the order",
        "laterality": "Laterality: L or R, which breast",
        "referring_physician": "ReferringPhysicianName, as 'Family^Given'",
        "study_description": "StudyDescription",
    }
    for name in STUDY_OPTIONS:
        p.add_argument(
            f"--{name.replace('_', '-')}", default="", help=f"study context: DICOM {study_help[name]} (default: empty)"
        )
    p.set_defaults(func=cmd_export)

    p = command("calibrate", "fit E and kappa from a calibration scan; write the updated calibration.json")
    p.add_argument("scan", type=Path, help="calibration scan folder (with imu.csv for kappa)")
    p.add_argument("--out", type=Path, default=None, help="where to write (default: SCAN/calibration.json)")
    p.set_defaults(func=cmd_calibrate)
