"""The pose graph's linear solves: SuperLU's symmetric mode against spsolve's default, on a scan's real final pass.

    .venv/bin/python bench/pose_graph_solve.py [--scan raster] [--scan exam] [--scan ../shared/scans/clinical_veins_24]
                                               [--repeat 3]

Each robust iteration of the pose graph (services/core/registration/pose_graph.py) solves symmetric positive
definite normal equations, 4 unknowns a free frame. This bench reconstructs a scan offline with `best` (a --scan
is a simulated scenario's name, seed 1, or a scan folder), records every normal matrix and right side the finish
solves (the final pass and the scale pass), then times, on each, scipy's spsolve with its default column ordering
(COLAMD: the baseline) and pose_graph.solve_normal (SuperLU in symmetric mode: minimum degree on A + A^T, diagonal
pivots); best of --repeat per solve, summed over the finish's solves. The last column is the largest difference
between the two solutions (the unknowns are mm and mm-scaled: a difference of 1e-9 is far below anything
measured).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def finish_systems(scan_name: str) -> list[tuple[object, np.ndarray]]:
    """Return the (normal matrix, right side) of every solve the finish of a scan's offline reconstruction makes
    (pipeline.reconstruct with `best`, its solves recorded while SessionReconstruction.finish runs)."""
    import services.core.registration.pose_graph as pose_graph
    from services.core.methods import method_options
    from services.core.pipeline import reconstruct
    from services.core.session_reconstruction import SessionReconstruction
    from services.core.simulation.scenarios import simulate
    from services.store.scan_folder import read_scan_folder

    scan = read_scan_folder(scan_name) if os.sep in scan_name else simulate(scan_name, 1)
    systems: list[tuple[object, np.ndarray]] = []
    finishing = [False]
    solve, finish = pose_graph.solve_normal, SessionReconstruction.finish

    def recording(normal: object, rhs: np.ndarray) -> np.ndarray:
        if finishing[0]:
            systems.append((normal.copy(), rhs.copy()))  # type: ignore[attr-defined]
        return solve(normal, rhs)  # type: ignore[arg-type]

    def recorded_finish(session: SessionReconstruction) -> set[tuple[int, int]]:
        finishing[0] = True
        try:
            return finish(session)
        finally:
            finishing[0] = False

    pose_graph.solve_normal = recording
    SessionReconstruction.finish = recorded_finish  # type: ignore[method-assign]
    try:
        reconstruct(scan, method_options("best"))
    finally:
        pose_graph.solve_normal, SessionReconstruction.finish = solve, finish  # type: ignore[method-assign]
    return systems


def best_seconds(solver: object, normal: object, rhs: np.ndarray, repeat: int) -> tuple[float, np.ndarray]:
    """Return the best wall seconds of `repeat` solves and the solution."""
    best, x = float("inf"), np.zeros(0)
    for _ in range(repeat):
        started = time.perf_counter()
        x = solver(normal, rhs)  # type: ignore[operator]
        best = min(best, time.perf_counter() - started)
    return best, x


def main() -> int:
    """Print the table: per scan, the finish's solves timed with both solvers."""
    from scipy.sparse.linalg import spsolve

    from services.core.normal_equations import solve_normal

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scan", action="append", default=None, help="a simulated scenario or a scan folder")
    p.add_argument("--repeat", type=int, default=3, help="solves per system (the best is kept)")
    args = p.parse_args()
    scans = args.scan or ["raster"]
    print("the finish's pose-graph solves: spsolve (COLAMD, baseline) against solve_normal (symmetric mode)\n")
    print("| scan | solves | unknowns | nonzeros | spsolve ms | solve_normal ms | ratio | max difference |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in scans:
        systems = finish_systems(name)
        base = new = 0.0
        diff = 0.0
        for normal, rhs in systems:
            t0, x0 = best_seconds(spsolve, normal, rhs, args.repeat)
            t1, x1 = best_seconds(solve_normal, normal, rhs, args.repeat)
            base, new = base + t0, new + t1
            diff = max(diff, float(np.max(np.abs(x1 - x0))))
        shape = systems[0][0].shape[0] if systems else 0  # type: ignore[attr-defined]
        nnz = systems[0][0].nnz if systems else 0  # type: ignore[attr-defined]
        label = Path(name).name if os.sep in name else name
        print(
            f"| {label} | {len(systems)} | {shape} | {nnz} | {1000 * base:.0f} | {1000 * new:.0f} | "
            f"{base / max(new, 1e-12):.2f}x | {diff:.1e} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
