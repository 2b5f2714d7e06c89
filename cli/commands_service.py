"""The commands of the running service: serve, worker, upload and demo (over HTTP), and send (to a PACS)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from cli import output

if TYPE_CHECKING:
    from cli.launcher import Service
    from services.settings import Settings


def cmd_send(args: argparse.Namespace) -> int:
    """Return the exit code of sending a results folder's DICOM files (*.dcm) to a PACS: 1 unless it stored all."""
    import dataclasses

    from services.pacs.destinations import DimseDestination, check_ae_title, parse_target
    from services.pacs.objects import read_objects
    from services.pacs.send import PacsError, send_objects
    from services.settings import Settings

    settings = Settings()
    files = sorted(Path(args.results).rglob("*.dcm"))
    if not files:
        raise ValueError(f"{args.results}: no DICOM files (*.dcm); write them with `veinmosaic export` first")
    destination = settings.pacs_destinations.get(args.to) or parse_target(args.to)
    if args.calling_ae and isinstance(destination, DimseDestination):
        destination = dataclasses.replace(destination, calling_ae=check_ae_title(args.calling_ae, "--calling-ae"))
    data = [f.read_bytes() for f in files]
    names: dict[str, Path] = {}
    for f, d in zip(files, data, strict=True):
        try:
            (obj,) = read_objects([d])
        except ValueError:
            raise ValueError(f"{f}: not a DICOM Part 10 file with SOP Class, Instance and Syntax UIDs") from None
        if obj.sop_instance_uid in names:
            raise ValueError(f"{f}: the same SOP Instance UID as {names[obj.sop_instance_uid]}")
        names[obj.sop_instance_uid] = f
    try:
        outcome = send_objects(destination, data, args.timeout or settings.pacs_timeout_s)
    except PacsError as exc:
        print(f"veinmosaic: send failed: {exc}", file=sys.stderr)
        return 1
    for uid in outcome.stored:
        print(f"stored {names[uid]} ({uid})")
    for uid, reason in outcome.failed.items():
        print(f"REFUSED {names[uid]} ({uid}): {reason}")
    print(f"{outcome.sent}/{len(files)} instance(s) stored at {outcome.destination} in {outcome.elapsed_s:.1f} s")
    return 0 if outcome.ok else 1


def _settings_for(args: argparse.Namespace) -> Settings:
    """Read the settings (once, for this command) and fill the service options left out from them."""
    from services.settings import get_settings

    settings = get_settings()
    for name in ("host", "port", "workers", "data_dir"):
        if getattr(args, name, None) is None:
            setattr(args, name, getattr(settings, name))
    return settings


def _service(args: argparse.Namespace, settings: Settings, extra_env: dict[str, str] | None = None) -> Service:
    from cli.launcher import Service

    return Service(
        data_dir=args.data_dir,
        host=args.host,
        port=args.port,
        workers=args.workers,
        redis_url=settings.redis_url,
        extra_env=extra_env or {},
        settings=settings,
    )


def cmd_serve(args: argparse.Namespace) -> int:
    """Return the exit code of running the API and N workers until interrupted.

    An embedded Redis runs too when REDIS_URL is unset.
    """
    service = _service(args, _settings_for(args))
    with service:
        print(f"veinmosaic serving on {service.base_url} with {args.workers} worker(s); data in {service.data_dir}")
        return service.wait()


def worker_argv() -> list[str]:
    """Return the command line of one worker process (`python -m workers.main`, this interpreter)."""
    return [sys.executable, "-m", "workers.main"]


def cmd_worker(args: argparse.Namespace) -> int:
    """Return never: exec one worker process against the configured Redis and storage (cli never imports workers)."""
    argv = worker_argv()
    os.execv(argv[0], argv)
    return 0  # not reached


def cmd_upload(args: argparse.Namespace) -> int:
    """Return the exit code 0 after uploading a scan folder to a running server, as a hospital system would."""
    from cli.client import VeinmosaicClient, upload_scan_folder

    client = VeinmosaicClient(args.url, args.key)

    def started(created: dict) -> None:
        print(f"session {created['id']}; viewer: {args.url.rstrip('/')}{created.get('viewer_url', '')}")

    with output.bar("upload") as bar:
        sid = upload_scan_folder(
            client, args.scan, label=args.label, realtime=args.realtime, progress=output.sized(bar), on_session=started
        )
    if args.wait:
        state = client.wait_done(sid, timeout_s=args.timeout)
        print(json.dumps(state, indent=2))
        output.print_warnings(state.get("warnings", []))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Return the exit code of a demo: serve, simulate a scan, upload it over HTTP, wait for the result and show it.

    Shown: the report, the images, the viewer.
    """
    data_dir = args.data_dir
    settings = _settings_for(args)
    args.data_dir = data_dir  # the demo's own default: a throw-away data dir, not the configured one
    with contextlib.ExitStack() as stack:
        if args.data_dir is None:  # a throw-away data dir: a demo run must not leave its uploads behind
            args.data_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="veinmosaic-demo-")))
            kept = "deleted when the demo ends"
        else:
            kept = "kept"
        return _run_demo(args, settings, kept)
    return 1  # unreachable: for type checkers


def _run_demo(args: argparse.Namespace, settings: Settings, kept: str) -> int:
    import secrets

    import httpx

    from cli.client import VeinmosaicClient, upload_scan_folder
    from cli.launcher import free_port
    from services.core.simulation.scenarios import simulate
    from services.store.scan_folder import write_scan_folder

    key = "demo-" + secrets.token_urlsafe(24)
    keys = json.loads(os.environ.get("VEINMOSAIC_API_KEYS") or "{}")
    keys[key] = ["ingest", "view", "admin"]
    if args.port == 0:
        args.port = free_port(args.host)
    # the demo's own output is the story; the service logs only warnings (JSON lines on stderr)
    service = _service(args, settings, {"VEINMOSAIC_API_KEYS": json.dumps(keys), "VEINMOSAIC_LOG_LEVEL": "WARNING"})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with service, tempfile.TemporaryDirectory() as tmp:
        print(f"1/4 serving on {service.base_url} ({args.workers} workers; data in {service.data_dir}, {kept})")
        scan_dir = Path(tmp) / "scan"
        scan = simulate(args.scenario, args.seed)
        write_scan_folder(scan, scan_dir)
        print(f"2/4 simulated a {args.scenario} scan: {len(scan)} frames, {scan.truth['path_length_mm']:.0f} mm")
        client = VeinmosaicClient(service.base_url, key)
        viewer = {}

        def started(created: dict) -> None:
            viewer["url"] = service.base_url + created.get("viewer_url", f"/viewer/{created['id']}")
            tqdm.write("   open the live viewer (this link is valid while the demo serves):")
            tqdm.write(viewer["url"])

        with output.bar("3/4 upload", len(scan)) as bar:
            sid = upload_scan_folder(
                client, scan_dir, label="demo", realtime=args.realtime, progress=output.sized(bar), on_session=started
            )
        with output.bar("4/4 processing", len(scan)) as bar:

            def shown(state: dict) -> None:
                bar.n = int(state.get("frames_processed", 0))
                bar.refresh()

            state = client.wait_done(sid, timeout_s=args.timeout, progress=shown)
        report = client.post_reference(sid, (scan_dir / "reference.csv").read_text())
        state = client.session(sid)
        base = f"/v1/sessions/{sid}"
        downloads = [
            ("mosaic.png", f"{base}/mosaic.png"),
            ("force.png", f"{base}/mosaic.png?layer=force"),
            ("coverage.png", f"{base}/mosaic.png?layer=coverage"),
            ("sheet.png", f"{base}/sheet.png"),
            ("sheet.pdf", f"{base}/sheet.pdf"),
            *[
                (f"{layer}.dcm", f"{base}/export.dcm?layer={layer}")
                for layer in ("vein", "force", "coverage", "report")
            ],
            *[(Path(u.split("?")[0]).name, u) for u in report.get("plots", {}).values() if str(u).startswith("/")],
        ]
        for name, url in downloads:
            try:
                (out / name).write_bytes(client.request("GET", url).content)
            except (httpx.HTTPError, RuntimeError) as exc:  # said, not hidden: the rest of the demo still runs
                print(f"   could not fetch {name}: {exc}")
        _write_scaled_maps(Path(service.data_dir), sid, out)
        registered = state.get("registered_fraction")
        print(
            f"session {state['status']}: {state.get('frames_processed')} frames processed, "
            f"{state.get('frames_lost', 0)} not placed"
            + (f", {100 * registered:.1f} % registered" if registered is not None else "")
        )
        print(f"accuracy vs the simulator's ground truth: {report.get('accuracy_summary', '')}")
        output.print_global_error(report.get("global_error"))
        output.print_warnings(state.get("warnings", []))
        print(f"images, scaled force and coverage maps, one-page report (sheet.pdf) and DICOM files in {out.resolve()}")
        print("viewer:")
        print(viewer.get("url", "(no session)"))
        if args.hold:
            print("--hold: serving until Ctrl-C ...", flush=True)
            with contextlib.suppress(KeyboardInterrupt):
                service.wait()
        else:
            print("the demo ends now and stops the service (the viewer link stops working); --hold keeps it serving")
    return 0 if state["status"] == "done" else 1


def _write_scaled_maps(data_dir: Path, sid: str, out: Path) -> None:
    """Write force_map.png and coverage_map.png: the finished layers in mm with colour scales (N; frames).

    force.png and coverage.png are the viewer's layers as served (colours without a scale); these are the maps a
    person reads, drawn from the finished layers in the demo's own data dir (the API serves no scaled map).
    """
    from services.core.outputs.plots import plot_coverage_map, plot_force_map
    from services.store.results_store import ResultsStore

    rs = ResultsStore(data_dir)
    try:
        version = rs.current_version(sid)
        mosaic = rs.read_mosaic_layers(sid, version) if version is not None else None
    except (OSError, ValueError):
        mosaic = None
    if mosaic is None:
        print("   could not draw force_map.png and coverage_map.png: no finished layers in the data dir")
        return
    (out / "force_map.png").write_bytes(plot_force_map(mosaic.force_n, mosaic.px_per_mm, mosaic.origin_px))
    (out / "coverage_map.png").write_bytes(plot_coverage_map(mosaic.coverage, mosaic.px_per_mm, mosaic.origin_px))


def _add_service_args(p: argparse.ArgumentParser, port: int | None, data_dir_help: str) -> None:
    """Add --host, --port, --workers, --data-dir; left out, they come from the settings (services.settings)."""
    from services.settings import Settings

    defaults = Settings.model_fields
    host, workers = defaults["host"].default, defaults["workers"].default
    p.add_argument("--host", default=None, help=f"interface the API listens on (default: VEINMOSAIC_HOST, else {host})")
    if port is None:
        port_help = f"API port (default: VEINMOSAIC_PORT, else {defaults['port'].default})"
    else:
        port_help = "API port (0: a free port)"
    p.add_argument("--port", type=int, default=port, help=port_help)
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"worker processes to start (default: VEINMOSAIC_WORKERS, else {workers})",
    )
    p.add_argument("--data-dir", type=Path, default=None, help=data_dir_help)


def add_commands(command: Callable[[str, str], argparse.ArgumentParser]) -> None:
    """Add send, serve, worker, upload and demo to the parser (`command(name, help)` adds one)."""
    p = command("send", "send a results folder's DICOM files (*.dcm, e.g. from `veinmosaic export`) to a PACS")
    p.add_argument("results", type=Path, help="folder searched for *.dcm files (with its subfolders)")
    p.add_argument(
        "--to",
        required=True,
        metavar="URL|HOST:PORT:AET|NAME",
        help="a DICOMweb base URL (STOW-RS), a DICOM peer HOST:PORT:AET (C-STORE), or a destination named in "
        "VEINMOSAIC_PACS_DESTINATIONS (required)",
    )
    p.add_argument("--calling-ae", default=None, help="our AE title for C-STORE (default: VEINMOSAIC)")
    p.add_argument(
        "--timeout", type=float, default=None, help="seconds per network step (default: VEINMOSAIC_PACS_TIMEOUT_S)"
    )
    p.set_defaults(func=cmd_send)

    p = command("serve", "run the API and workers (an embedded Redis when REDIS_URL is unset) until Ctrl-C")
    _add_service_args(p, None, "uploads and results (default: VEINMOSAIC_DATA_DIR, else ./data)")
    p.set_defaults(func=cmd_serve)

    p = command("worker", "run one worker process against REDIS_URL and VEINMOSAIC_DATA_DIR")
    p.set_defaults(func=cmd_worker)

    p = command("upload", "upload a scan folder to a running server, as a hospital system would")
    p.add_argument("scan", type=Path, help="scan folder (spec §3)")
    p.add_argument("--url", required=True, help="server base URL, e.g. http://127.0.0.1:8000 (required)")
    p.add_argument("--key", required=True, help="API key with scope ingest (required)")
    p.add_argument("--label", default="", help="session label (stored, never logged; default: none)")
    p.add_argument("--realtime", type=float, default=0.0, help="pace at this multiple of the recorded rate (0: fast)")
    p.add_argument(
        "--wait",
        action="store_true",
        help="wait until processing is done and print the state (default: return after the upload)",
    )
    p.add_argument("--timeout", type=float, default=900.0, help="seconds to wait with --wait")
    p.set_defaults(func=cmd_upload)

    p = command(
        "demo",
        "serve, simulate a scan, upload it over HTTP and show the result; stops serving at the end unless --hold",
    )
    _add_service_args(p, 0, "data dir to use and keep (default: a temporary one, deleted at the end)")
    p.add_argument("--scenario", default="revisit", choices=["raster", "revisit", "hard", "short"], help="kind of scan")
    p.add_argument("--seed", type=int, default=1, help="random seed of the simulated scan")
    p.add_argument(
        "--realtime", type=float, default=0.0, help="pace the upload at this multiple of real time (0: fast)"
    )
    p.add_argument("--out", type=Path, default=Path("demo-out"), help="folder for images, report and DICOM files")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds to wait for processing")
    p.add_argument(
        "--hold",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="keep serving (and the viewer link working) after the demo until Ctrl-C (default: stop at the end)",
    )
    p.set_defaults(func=cmd_demo)
