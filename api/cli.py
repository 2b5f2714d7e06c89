"""The `veinmosaic` command line: a thin shell over services/ (and, for serving, over api/ and workers/)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

if TYPE_CHECKING:
    from api.launcher import Service


def _sized(bar: tqdm) -> Callable[[int, int], None]:
    """Return a progress callback (done, total) that drives a tqdm bar."""

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return update


def _bar(desc: str, total: int = 0) -> tqdm:
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True)


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
    options = method_options(args.method).with_overrides(_parse_options(args.option))
    with _bar(f"reconstruct ({args.method})", len(scan)) as bar:
        recon = reconstruct(scan, options, progress=_sized(bar))
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


def _parse_options(pairs: list[str]) -> dict[str, object]:
    """Return method overrides from KEY=VALUE strings, each value typed like the option's default."""
    from dataclasses import fields

    from services.methods import MethodOptions

    types = {f.name: f.type for f in fields(MethodOptions)}
    out: dict[str, object] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in types:
            raise ValueError(f"--option {pair!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(types))}")
        kind = types[key]
        if kind == "bool":
            out[key] = value.lower() in ("1", "true", "yes", "on")
        elif kind == "int":
            out[key] = int(value)
        elif kind == "float":
            out[key] = float(value)
        else:
            out[key] = value
    return out


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


def _service(args: argparse.Namespace, extra_env: dict[str, str] | None = None) -> Service:
    from api.launcher import Service
    from api.settings import get_settings

    settings = get_settings()
    data_dir = args.data_dir or settings.data_dir
    return Service(
        data_dir=data_dir,
        host=args.host,
        port=args.port,
        workers=args.workers,
        redis_url=settings.redis_url,
        extra_env=extra_env or {},
    )


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the API and N workers (and an embedded Redis when REDIS_URL is unset) until interrupted."""
    service = _service(args)
    with service:
        print(f"veinmosaic serving on {service.base_url} with {args.workers} worker(s); data in {service.data_dir}")
        return service.wait()


def cmd_worker(args: argparse.Namespace) -> int:
    """Run one worker process against the configured Redis and storage."""
    from workers.main import main as worker_main

    return int(worker_main([]) or 0)


def cmd_upload(args: argparse.Namespace) -> int:
    """Upload a scan folder to a running server, as a hospital system would."""
    from api.client import VeinmosaicClient, upload_scan_folder

    client = VeinmosaicClient(args.url, args.key)

    def started(created: dict) -> None:
        print(f"session {created['id']}; viewer: {args.url.rstrip('/')}{created.get('viewer_url', '')}")

    with _bar("upload") as bar:
        sid = upload_scan_folder(
            client, args.scan, label=args.label, realtime=args.realtime, progress=_sized(bar), on_session=started
        )
    if args.wait:
        state = client.wait_done(sid, timeout_s=args.timeout)
        print(json.dumps(state, indent=2))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Serve, simulate a scan, upload it over HTTP, wait for the result and show it (report, images, viewer)."""
    import os
    import secrets
    import tempfile

    import httpx

    from api.client import VeinmosaicClient, upload_scan_folder
    from services.scan_folder import write_scan_folder
    from services.simulation.scenarios import simulate

    key = "demo-" + secrets.token_urlsafe(12)
    keys = json.loads(os.environ.get("VEINMOSAIC_API_KEYS") or "{}")
    keys[key] = ["ingest", "view", "admin"]
    if args.port == 0:
        args.port = _free_port(args.host)
    # the demo's own output is the story; the service logs only warnings (JSON lines on stderr)
    service = _service(args, {"VEINMOSAIC_API_KEYS": json.dumps(keys), "VEINMOSAIC_LOG_LEVEL": "WARNING"})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with service, tempfile.TemporaryDirectory() as tmp:
        print(f"1/4 serving on {service.base_url} ({args.workers} workers, data in {service.data_dir})")
        scan_dir = Path(tmp) / "scan"
        scan = simulate(args.scenario, args.seed)
        write_scan_folder(scan, scan_dir)
        print(f"2/4 simulated a {args.scenario} scan: {len(scan)} frames, {scan.truth['path_length_mm']:.0f} mm")
        client = VeinmosaicClient(service.base_url, key)
        viewer = {}

        def started(created: dict) -> None:
            viewer["url"] = service.base_url + created.get("viewer_url", f"/viewer/{created['id']}")
            print(f"   open the live viewer: {viewer['url']}")

        with _bar("3/4 upload", len(scan)) as bar:
            sid = upload_scan_folder(
                client, scan_dir, label="demo", realtime=args.realtime, progress=_sized(bar), on_session=started
            )
        with _bar("4/4 processing", len(scan)) as bar:

            def shown(state: dict) -> None:
                bar.n = int(state.get("frames_processed", 0))
                bar.refresh()

            state = client.wait_done(sid, timeout_s=args.timeout, progress=shown)
        report = client.post_reference(sid, (scan_dir / "reference.csv").read_text())
        for name, url in [
            ("mosaic.png", f"/v1/sessions/{sid}/mosaic.png"),
            ("force.png", f"/v1/sessions/{sid}/mosaic.png?layer=force"),
            *[(Path(u.split("?")[0]).name, u) for u in report.get("plots", {}).values() if str(u).startswith("/")],
        ]:
            with contextlib.suppress(httpx.HTTPError, RuntimeError):
                (out / name).write_bytes(client.request("GET", url).content)
        print(
            f"session {state['status']}: {state.get('frames_processed')} frames processed, "
            f"{state.get('frames_lost', 0)} lost"
        )
        print(
            f"accuracy vs the simulator's ground truth: RMSE {report['rmse_mm']:.3f} mm, final drift "
            f"{report['final_drift_mm']:.3f} mm, error ratio {report['error_ratio_pct']:.4f}% over "
            f"{report['path_length_mm']:.0f} mm, registered {100 * report['registered_fraction']:.1f}%"
        )
        print(f"images and plots in {out.resolve()}; viewer: {viewer.get('url')}")
        if args.hold:
            print("serving until Ctrl-C ...")
            service.wait()
    return 0 if state["status"] == "done" else 1


def _free_port(host: str) -> int:
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _add_service_args(p: argparse.ArgumentParser, port: int) -> None:
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=port)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--data-dir", type=Path, default=None, help="default: VEINMOSAIC_DATA_DIR or ./data")


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
    p.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a method option, e.g. features=asift (full ASIFT) or refine=false",
    )
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("calibrate", help="fit E and kappa from a calibration scan")
    p.add_argument("scan", type=Path)
    p.add_argument("--out", type=Path, default=None, help="default: SCAN/calibration.json")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("serve", help="run the API and workers (embedded Redis when REDIS_URL is unset)")
    _add_service_args(p, 8000)
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("worker", help="run one worker process")
    p.set_defaults(func=cmd_worker)

    p = sub.add_parser("upload", help="upload a scan folder to a server")
    p.add_argument("scan", type=Path)
    p.add_argument("--url", required=True)
    p.add_argument("--key", required=True)
    p.add_argument("--label", default="")
    p.add_argument("--realtime", type=float, default=0.0, help="pace at this multiple of the recorded rate")
    p.add_argument("--wait", action="store_true", help="wait until processing is done")
    p.add_argument("--timeout", type=float, default=900.0)
    p.set_defaults(func=cmd_upload)

    p = sub.add_parser("demo", help="serve, simulate a scan, upload it over HTTP and show the result")
    _add_service_args(p, 0)
    p.add_argument("--scenario", default="revisit", choices=["raster", "revisit", "hard", "short"])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--realtime", type=float, default=0.0)
    p.add_argument("--out", type=Path, default=Path("demo-out"))
    p.add_argument("--timeout", type=float, default=900.0)
    p.add_argument("--hold", action=argparse.BooleanOptionalAction, default=sys.stdout.isatty())
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the veinmosaic command line; return the exit code."""
    from services.calibration import CalibrationError
    from services.scan_folder import ScanFormatError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ScanFormatError, CalibrationError, ValueError) as exc:
        print(f"veinmosaic: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
