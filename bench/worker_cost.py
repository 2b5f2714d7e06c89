"""CPU per frame of a live worker's steps (issues 15, 32): where a frame's processing time goes, and what threads cost.

    .venv/bin/python bench/worker_cost.py [--frames 150] [--copies 1,2] [--threads 1,2] [--repo PATH ...]
                                          [--scan SCAN_FOLDER]

Each measurement runs in a child process doing in order what the service's workers do with each frame of a simulated
raster scan, on a temporary data dir: the upload decoded (the stored PNG read, its header checked, decoded:
SessionStore.load_frame), the frame prepared (rectify, vein map, features), its prepared file written (npz, written
once with fsync: ResultsStore.write_prepared) and read back by the register stage (read_prepared), the frame added to
a live SessionReconstruction (registration, refinement, canvas paste); every --flush-every frames a flush's work
(workers/stages/register/flush.py): the path rows and path.json, the pyramid update, the changed tiles' vein and
force PNGs (those of levels where one tile holds the whole canvas only with the images), their writes (no fsync, as
live), mosaic.json (read back, rebuilt with the extent and the learned model, written) and state.json; the whole
mosaic rendered and its images written every 20 frames (2 s of scan). It prints CPU milliseconds per frame by step
(the process's CPU time: all its threads), then the same in wall time (a step's disk waits are in it). A
configuration is a number of copies run at once (like that many busy workers on the machine), the BLAS/OpenCV
threads of each, and the source tree measured (--repo: e.g. `git archive <commit> | tar -x -C /tmp/old`, to compare
code in the same run). The first configuration is the baseline of the ratio column. --scan a scan folder (e.g.
../shared/scans/raster_veins_23) measures its first --frames frames instead of the simulated raster: the simulator's
vein maps hold about half the SIFT keypoints of the shared scans', so SIFT costs more on real frames (each copy runs
the same folder then).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARTS = (
    "decode", "prepare", "prepared_write", "prepared_read", "register", "path", "pyramid", "vein_tiles",
    "force_tiles", "tile_writes", "documents", "images",
)  # fmt: skip
WORK = ("prepare", "register")  # the algorithm; the other steps are the service's overhead


def measure(
    frames: int, flush_every: int, seed: int, overrides: dict[str, object], folder: str | None = None
) -> dict[str, float]:
    """Return CPU ms per frame of each step of a live worker's work on a simulated raster or a scan folder (this
    process)."""
    import cv2

    from services.core.methods import method_options
    from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
    from services.core.outputs.documents import canvas_extent_mm, empty_revisions, image_meta, mosaic_json
    from services.core.pipeline import frame_forces, prepare_scan_frame, window_radius_mm, window_setup
    from services.core.session_reconstruction import SessionReconstruction
    from services.core.simulation.scenarios import simulate
    from services.store.results_store import ResultsStore
    from services.store.scan_folder import read_scan_folder
    from services.store.storage import SessionStore
    from services.store.version_state import VersionState

    cv2.setNumThreads(int(os.environ.get("BENCH_CV_THREADS", "1")))
    scan = read_scan_folder(folder) if folder else simulate("raster", seed)
    options = method_options("best").with_overrides(overrides)
    calib = scan.calibration
    forces = frame_forces(scan)
    mask, flat = window_setup(scan, options)
    n = min(frames, len(scan))
    spent = dict.fromkeys(PARTS, 0.0)
    waited = dict.fromkeys(PARTS, 0.0)  # wall time
    clock = time.process_time
    with tempfile.TemporaryDirectory(prefix="vm-cost-", ignore_cleanup_errors=True) as tmp:
        store, results = SessionStore(Path(tmp)), ResultsStore(Path(tmp))
        sid = store.create_session(uuid.uuid4().hex * 2, "bench", calib).id
        results.ensure_version(sid, 1, {"method": options.name})
        seqs = [int(seq) for seq in scan.frame_seq[:n]]  # a frame is stored, prepared and registered by its seq
        for i, seq in enumerate(seqs):  # the uploads, as the API stores them (not measured: the API's work)
            png = cv2.imencode(".png", scan.frame(i))[1].tobytes()
            store.put_frame(sid, seq, float(scan.frame_t_s[i]), png, "png")
        recon = SessionReconstruction(calib, options, window_radius_mm(mask, calib), live=True)
        geometry = DziGeometry.for_mosaic(calib.px_per_mm, 200.0)
        pyramid = TilePyramid(geometry)
        touched: set[tuple[int, int]] = set()
        deferred: set[tuple[int, int, int]] = set()
        revisions = empty_revisions()
        t = (clock(), time.monotonic())

        def lap(part: str) -> None:
            nonlocal t
            now = (clock(), time.monotonic())
            spent[part] += now[0] - t[0]
            waited[part] += now[1] - t[1]
            t = now

        for i, seq in enumerate(seqs):
            for dropped in range(len(recon.results), seq):  # seqs the camera dropped: missing, as live
                recon.lose(dropped)
            t = (clock(), time.monotonic())
            raw = store.load_frame(sid, seq, expected_size=calib.image_size)
            lap("decode")
            # prepare_scan_frame reads the scan's own copy of the frame: the decoded upload is the same pixels
            assert raw.shape == scan.frame(i).shape
            pf = prepare_scan_frame(scan, i, forces[i], mask, flat, options)
            lap("prepare")
            results.write_prepared(sid, 1, pf)
            lap("prepared_write")
            pf = results.read_prepared(sid, 1, seq)
            lap("prepared_read")
            touched |= recon.add(pf)[1]
            lap("register")
            if i % flush_every == flush_every - 1:
                rows = recon.path_rows()
                results.write_path(sid, 1, rows)
                lap("path")
                deferred |= pyramid.update(recon.canvas, touched)
                touched = set()
                with_images = i % 20 >= 20 - flush_every  # the flush that writes the whole images (below)
                changed = {k for k in deferred if with_images or geometry.tiles_at(k[0]) != (1, 1)}
                deferred -= changed  # levels where one tile holds the whole canvas wait for the images (flush.py)
                lap("pyramid")
                pngs = {(key, layer): pyramid.render_png(*key, layer) for key in changed for layer in ("vein",)}
                lap("vein_tiles")
                pngs.update({(key, layer): pyramid.render_png(*key, layer) for key in changed for layer in ("force",)})
                lap("force_tiles")
                for ((level, col, row), layer), png in pngs.items():
                    if png is not None:
                        results.write_tile(sid, 1, layer, level, col, row, png, durable=False)
                    revisions.setdefault(layer, {})[f"{level}/{col}_{row}"] = i
                lap("tile_writes")
                doc = results.read_mosaic_meta(sid, 1) or {}
                doc = mosaic_json(
                    image_meta(doc, calib.px_per_mm),
                    version=int(doc.get("version", 0)) + 1,
                    results_version=1,
                    revisions=revisions,
                    geometry=geometry,
                    extent_mm=canvas_extent_mm(recon.canvas),
                    rows=rows,
                    status="receiving",
                    method=options.name,
                    tissue=recon.learned_model(),
                    placed=recon.placed_counts(),
                )
                results.write_mosaic_meta(sid, 1, doc)
                results.write_state(sid, 1, VersionState(i + 1, 1, False))
                lap("documents")
            if i % 20 == 19:
                results.write_mosaic_images(sid, 1, recon.canvas.render(), raw_layers=False)
                lap("images")
    return {
        **{part: 1000.0 * s / n for part, s in spent.items()},
        **{f"{p}_wall": 1000.0 * s / n for p, s in waited.items()},
    }


def run_config(args: argparse.Namespace, copies: int, threads: int, repo: Path, options: str) -> list[dict[str, float]]:
    """Return the per-part figures of `copies` children run at once on `repo` with `threads` BLAS/OpenCV threads,
    `best` with the method options `options` (JSON)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo)
    env["OPENBLAS_NUM_THREADS"] = str(threads)
    env["BENCH_CV_THREADS"] = str(threads)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--frames", str(args.frames)]
    cmd += ["--flush-every", str(args.flush_every), "--option-set", options]
    cmd += ["--scan", str(args.scan.resolve())] if args.scan else []
    procs = [
        subprocess.Popen([*cmd, "--seed", str(1 + k)], env=env, cwd=repo, stdout=subprocess.PIPE, text=True)
        for k in range(copies)
    ]
    out = []
    for p in procs:
        stdout, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"a measurement failed (exit {p.returncode})")
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def main() -> int:
    """Print the table of CPU ms per frame by part for every configuration (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=150, help="frames measured (the first)")
    p.add_argument("--flush-every", type=int, default=5, help="frames per flush (0.5 s at 10 frames/s)")
    p.add_argument("--copies", default="1,2", help="copies run at once (busy workers on the machine)")
    p.add_argument("--threads", default="1", help="BLAS and OpenCV threads per process, e.g. 1,2")
    p.add_argument("--repo", type=Path, action="append", default=None, help="source trees to measure")
    p.add_argument("--scan", type=Path, default=None, help="a scan folder instead of the simulated raster")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument(
        "--option-set",
        action="append",
        default=None,
        help='method options of `best` to measure (JSON), e.g. {"track_overlap": 0.85}',
    )
    args = p.parse_args()
    if args.child:
        overrides = json.loads(args.option_set[0])
        folder = str(args.scan) if args.scan else None
        print(json.dumps(measure(args.frames, args.flush_every, args.seed, overrides, folder)))
        return 0
    repos = args.repo or [REPO]
    configs = [
        (repo, copies, threads, options)
        for options in args.option_set or ["{}"]
        for repo in repos
        for threads in (int(t) for t in args.threads.split(","))
        for copies in (int(c) for c in args.copies.split(","))
    ]
    name = args.scan.name if args.scan else "raster"
    print(f"{name}, {args.frames} frames, a flush every {args.flush_every} frames; CPU ms per frame (mean of copies)")
    print()
    print("| tree | options | copies | threads | " + " | ".join(PARTS) + " | overhead | total | vs first |")
    print("|---|---|---:|---:|" + "---:|" * (len(PARTS) + 3))
    base = None
    walls = []
    for repo, copies, threads, options in configs:
        tree = repo.resolve().name  # '.' by its folder's name
        print(f"running {tree} {options}: {copies} copies x {threads} threads ...", file=sys.stderr)
        rows = run_config(args, copies, threads, repo, options)
        mean = {part: sum(r[part] for r in rows) / len(rows) for part in PARTS}
        total = sum(mean.values())
        overhead = total - sum(mean[part] for part in WORK)
        base = total if base is None else base
        cells = " | ".join(f"{mean[part]:.1f}" for part in PARTS)
        row = f"| {tree} | {options} | {copies} | {threads} | {cells} | {overhead:.1f} | {total:.1f} "
        row += f"| {total / base:.2f}x |"
        print(row, flush=True)
        wall = {part: sum(r[f"{part}_wall"] for r in rows) / len(rows) for part in PARTS}
        walls.append(
            f"| {tree} | {options} | {copies} | {threads} | " + " | ".join(f"{wall[p]:.1f}" for p in PARTS) + " |"
        )
    print("\nwall ms per frame (mean of copies): a step's waits (fsync, other processes) are in it\n")
    print("| tree | options | copies | threads | " + " | ".join(PARTS) + " |")
    print("|---|---|---:|---:|" + "---:|" * len(PARTS))
    print("\n".join(walls))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
