"""CPU per frame of a live worker's parts (issue 15): where a frame's processing time goes, and what threads cost.

    .venv/bin/python bench/worker_cost.py [--frames 150] [--copies 1,2] [--threads 1,2] [--repo PATH ...]

Each measurement runs in a child process, as a worker does in-process: a simulated raster scan's frames prepared
(rectify, vein map, features), added to a live SessionReconstruction (registration, refinement, canvas paste),
and every --flush-every frames a flush's tile work (pyramid update, the changed tiles' vein and force PNGs), the
whole mosaic rendered every 20 frames (2 s of scan). It prints CPU milliseconds per frame by part (the process's
CPU time: all its threads). A configuration is a number of copies run at once (like that many busy workers on
the machine), the BLAS/OpenCV threads of each, and the source tree measured (--repo: e.g. a `git worktree` of an
older commit, to compare code in the same run). The first configuration is the baseline of the ratio column.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARTS = ("prepare", "register", "pyramid", "vein_tiles", "force_tiles", "images")


def measure(frames: int, flush_every: int, seed: int) -> dict[str, float]:
    """Return CPU ms per frame of each part of a live worker's work on a simulated raster (this process)."""
    import cv2

    from services.core.methods import method_options
    from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
    from services.core.pipeline import frame_forces, prepare_scan_frame, window_radius_mm, window_setup
    from services.core.session_reconstruction import SessionReconstruction
    from services.core.simulation.scenarios import simulate

    cv2.setNumThreads(int(os.environ.get("BENCH_CV_THREADS", "1")))
    scan = simulate("raster", seed)
    options = method_options("best")
    calib = scan.calibration
    forces = frame_forces(scan)
    mask, flat = window_setup(scan, options)
    recon = SessionReconstruction(calib, options, window_radius_mm(mask, calib), live=True)
    pyramid = TilePyramid(DziGeometry.for_mosaic(calib.px_per_mm, 200.0))
    spent = dict.fromkeys(PARTS, 0.0)
    touched: set[tuple[int, int]] = set()
    n = min(frames, len(scan))
    clock = time.process_time
    for i in range(n):
        t0 = clock()
        pf = prepare_scan_frame(scan, i, forces[i], mask, flat, options)
        t1 = clock()
        touched |= recon.add(pf)[1]
        spent["prepare"] += t1 - t0
        spent["register"] += clock() - t1
        if i % flush_every == flush_every - 1:
            t0 = clock()
            changed = pyramid.update(recon.canvas, touched)
            touched = set()
            t1 = clock()
            for key in changed:
                pyramid.render_png(*key, "vein")
            t2 = clock()
            for key in changed:
                pyramid.render_png(*key, "force")
            spent["pyramid"] += t1 - t0
            spent["vein_tiles"] += t2 - t1
            spent["force_tiles"] += clock() - t2
        if i % 20 == 19:
            t0 = clock()
            recon.canvas.render()
            spent["images"] += clock() - t0
    return {part: 1000.0 * s / n for part, s in spent.items()}


def run_config(args: argparse.Namespace, copies: int, threads: int, repo: Path) -> list[dict[str, float]]:
    """Return the per-part figures of `copies` children run at once on `repo` with `threads` BLAS/OpenCV threads."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo)
    env["OPENBLAS_NUM_THREADS"] = str(threads)
    env["BENCH_CV_THREADS"] = str(threads)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--frames", str(args.frames)]
    cmd += ["--flush-every", str(args.flush_every)]
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
    p.add_argument("--frames", type=int, default=150, help="frames of the simulated raster measured")
    p.add_argument("--flush-every", type=int, default=5, help="frames per flush (0.5 s at 10 frames/s)")
    p.add_argument("--copies", default="1,2", help="copies run at once (busy workers on the machine)")
    p.add_argument("--threads", default="1", help="BLAS and OpenCV threads per process, e.g. 1,2")
    p.add_argument("--repo", type=Path, action="append", default=None, help="source trees to measure")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(measure(args.frames, args.flush_every, args.seed)))
        return 0
    repos = args.repo or [REPO]
    configs = [
        (repo, copies, threads)
        for repo in repos
        for threads in (int(t) for t in args.threads.split(","))
        for copies in (int(c) for c in args.copies.split(","))
    ]
    print(f"raster, {args.frames} frames, a flush every {args.flush_every} frames; CPU ms per frame (mean of copies)")
    print()
    print("| tree | copies | threads | " + " | ".join(PARTS) + " | total | vs first |")
    print("|---|---:|---:|" + "---:|" * (len(PARTS) + 2))
    base = None
    for repo, copies, threads in configs:
        print(f"running {repo.name}: {copies} copies x {threads} threads ...", file=sys.stderr)
        rows = run_config(args, copies, threads, repo)
        mean = {part: sum(r[part] for r in rows) / len(rows) for part in PARTS}
        total = sum(mean.values())
        base = total if base is None else base
        cells = " | ".join(f"{mean[part]:.1f}" for part in PARTS)
        print(f"| {repo.name} | {copies} | {threads} | {cells} | {total:.1f} | {total / base:.2f}x |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
