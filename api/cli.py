"""The `veinmosaic` command line: a thin shell over services/ (and, for serving, over api/ and workers/)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from tqdm import tqdm


def _progress_bar(total: int, desc: str) -> tuple[tqdm, object]:
    bar = tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True)

    def update(done: int, _total: int) -> None:
        bar.n = done
        bar.refresh()

    return bar, update


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a simulated scan folder (spec §3) with reference.csv."""
    from services.scan_folder import write_scan_folder
    from services.simulation.scenarios import simulate

    scan = simulate(args.scenario, args.seed)
    write_scan_folder(scan, args.out)
    length = scan.truth.get("path_length_mm", float("nan"))
    print(f"wrote {len(scan)} frames ({args.scenario}, seed {args.seed}, path {length:.0f} mm) to {args.out}")
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    """Reconstruct a scan folder and write path, mosaic, force layer and (with a reference) the report."""
    from services.methods import method_options
    from services.pipeline import reconstruct
    from services.results_io import write_reconstruction
    from services.scan_folder import read_scan_folder

    scan = read_scan_folder(args.scan)
    options = method_options(args.method)
    bar, update = _progress_bar(len(scan), f"reconstruct ({args.method})")
    with bar:
        recon = reconstruct(scan, options, progress=update)
    report = write_reconstruction(recon, args.out, scan.reference_mm)
    ok = int(recon.registered.sum())
    print(f"{ok}/{len(scan)} frames registered in {recon.seconds:.1f} s; outputs in {args.out}")
    if report is not None:
        print(
            f"RMSE {report.rmse_mm:.3f} mm, max {report.max_error_mm:.3f} mm, final drift "
            f"{report.final_drift_mm:.3f} mm, error ratio {report.error_ratio_pct:.3f}% over "
            f"{report.path_length_mm:.0f} mm"
        )
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Fit E and kappa from a calibration scan; print the fits and write an updated calibration.json."""
    from services.calibration_fit import calibrate_scan, format_calibration_report
    from services.scan_folder import read_scan_folder

    scan = read_scan_folder(args.scan)
    result = calibrate_scan(scan)
    print(format_calibration_report(result))
    out = Path(args.out) if args.out else Path(args.scan) / "calibration.json"
    out.write_text(json.dumps(result.calibration.to_dict(), indent=2))
    print(f"wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of the veinmosaic command."""
    parser = argparse.ArgumentParser(prog="veinmosaic", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="write a simulated scan folder")
    p.add_argument("--scenario", default="short", choices=["raster", "revisit", "hard", "short", "calib"])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", required=True, type=Path)
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("reconstruct", help="reconstruct a scan folder offline")
    p.add_argument("scan", type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--method", default="best", choices=["sift-chain", "paper", "best"])
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("calibrate", help="fit E and kappa from a calibration scan")
    p.add_argument("scan", type=Path)
    p.add_argument("--out", type=Path, default=None, help="default: SCAN/calibration.json")
    p.set_defaults(func=cmd_calibrate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the veinmosaic command line; return the exit code."""
    from services.calibration import CalibrationError
    from services.scan_folder import ScanFormatError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ScanFormatError, CalibrationError) as exc:
        print(f"veinmosaic: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
