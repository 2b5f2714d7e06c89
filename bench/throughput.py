"""Throughput and memory benchmark: can the pipeline keep up with the probe (about 10 frames/s, 2 cores)?

Usage: python bench/throughput.py [--scenario raster] [--frames 120] [--seed 1]
Per method, on the same simulated frames in one process: CPU seconds per frame of the parallel stage
(undistort + rectify + features) and of the sequential stage (registration), the wall-clock frames/s of
the whole offline pipeline (preparation on 2 threads ahead of registration), and the ratio to `paper`.
Then the mosaic canvas memory: sparse tiles against a dense canvas of the same bounding box.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.core.inputs.scan import Scan, in_memory_loader
from services.core.methods import method_options
from services.core.mosaic.canvas import PLANES, TILE_PX
from services.core.pipeline import frame_forces, prepare_scan_frame, reconstruct, window_radius_mm, window_setup
from services.core.session_reconstruction import SessionReconstruction
from services.core.simulation.scenarios import simulate

TARGET_FPS = 10.0


def truncate(scan: Scan, n: int) -> Scan:
    """Return the first n frames of a scan (forces and reference kept whole)."""
    frames = [scan.frame(i) for i in range(min(n, len(scan)))]
    return Scan(
        calibration=scan.calibration,
        frame_seq=scan.frame_seq[: len(frames)],
        frame_t_s=scan.frame_t_s[: len(frames)],
        force_t_s=scan.force_t_s,
        forces_n=scan.forces_n,
        frame_loader=in_memory_loader(frames),
        mask=scan.mask,
        reference_mm=None if scan.reference_mm is None else scan.reference_mm[: len(frames)],
    )


def stage_costs(scan: Scan, method: str) -> tuple[float, float, SessionReconstruction]:
    """Return (prepare s/frame, register s/frame, the session) of a method, one stage at a time (CPU time)."""
    options = method_options(method)
    forces, (mask, flat) = frame_forces(scan), window_setup(scan, options)
    t0 = time.process_time()
    prepared = [prepare_scan_frame(scan, i, forces[i], mask, flat, options) for i in range(len(scan))]
    t1 = time.process_time()
    session = SessionReconstruction(scan.calibration, options, window_radius_mm(mask, scan.calibration))
    for pf in prepared:
        session.add(pf)
    session.finish()
    t2 = time.process_time()
    session.render()
    return (t1 - t0) / len(scan), (t2 - t1) / len(scan), session


def main() -> int:
    """Print the throughput table and the canvas memory table; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="raster")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--methods", default="paper,sift-chain,best")
    args = parser.parse_args()
    import cv2

    cv2.setNumThreads(1)  # stage costs on one core; the wall-clock column uses the pipeline's 2 threads
    scan = truncate(simulate(args.scenario, args.seed), args.frames)
    rows = []
    for method in args.methods.split(","):
        prep, reg, session = stage_costs(scan, method)
        started = time.perf_counter()
        recon = reconstruct(scan, method_options(method))
        wall = (time.perf_counter() - started) / len(scan)
        rows.append((method, prep, reg, 1.0 / wall, session))
        del recon
    base = next((r for r in rows if r[0] == "paper"), rows[0])
    print(f"{args.scenario}, first {len(scan)} frames; CPU s/frame per stage on 1 core; wall fps on 2 threads")
    ratio = f"x {base[0]}"
    print(f"{'method':<11}| {'prepare s/f':>11} | {'register s/f':>12} | {'wall fps':>8} | {ratio:>12} | keeps up")
    print("-" * 77)
    for method, prep, reg, fps, _ in rows:
        # two cores: preparation splits across both, registration is sequential on one
        two_core_fps = 1.0 / max(reg, (prep + reg) / 2)
        keeps = "yes" if min(fps, two_core_fps) >= TARGET_FPS else "no"
        print(f"{method:<11}| {prep:>11.3f} | {reg:>12.3f} | {fps:>8.1f} | {fps / base[3]:>12.1f} | {keeps}")
    canvas = rows[-1][4].canvas
    c0, r0, c1, r1 = canvas.extent_tiles()
    tile_bytes = TILE_PX * TILE_PX * PLANES * 4
    dense = (c1 - c0 + 1) * (r1 - r0 + 1) * tile_bytes
    sparse = len(canvas.tiles) * tile_bytes
    print(f"\ncanvas memory ({rows[-1][0]}, float32 planes): sparse tiles against a dense bounding box")
    print(f"{'canvas':<8}| {'tiles':>5} | {'MiB':>6} | {'x dense':>7}")
    print(f"{'dense':<8}| {(c1 - c0 + 1) * (r1 - r0 + 1):>5} | {dense / 2**20:>6.1f} | {1.0:>7.2f}")
    print(f"{'sparse':<8}| {len(canvas.tiles):>5} | {sparse / 2**20:>6.1f} | {sparse / dense:>7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
