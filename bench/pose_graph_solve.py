"""The pose graph's linear solves on a scan's real finish: spsolve's default, SuperLU's symmetric mode, and that
factor reused across a robust fit's reweighted iterations.

    .venv/bin/python bench/pose_graph_solve.py [--scan raster] [--scan exam] [--scan ../shared/scans/clinical_veins_24]
                                               [--repeat 3]

Each robust iteration of the pose graph (services/core/registration/pose_graph.py) solves symmetric positive
definite normal equations, 4 unknowns a free frame; one optimisation's iterations differ only in their weights.
This bench reconstructs a scan offline with `best` (a --scan is a simulated scenario's name, seed 1, or a scan
folder), records every normal matrix and right side the finish solves (the final pass and the scale pass), each
optimisation's run apart, then times on them: scipy's spsolve with its default column ordering (COLAMD: the
baseline), normal_equations.solve_normal on each system (SuperLU in symmetric mode: minimum degree on A + A^T,
diagonal pivots), and normal_equations.NormalSolver through each run (what pose_graph.optimise_poses uses: the run's
first system factored, the next ones solved by conjugate gradients on that factor). Best of --repeat, summed over
the finish's solves. The difference columns are the largest against spsolve's solutions (the unknowns are mm and
mm-scaled: a difference of 1e-9 is far below anything measured).
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

Run = list[tuple[object, np.ndarray]]  # one optimisation's (normal matrix, right side), in order


def finish_runs(scan_name: str) -> list[Run]:
    """Return the systems every optimisation of a scan's offline finish solves, one list per optimisation
    (pipeline.reconstruct with `best`, its solves recorded while SessionReconstruction.finish runs)."""
    from services.core import normal_equations
    from services.core.methods import method_options
    from services.core.pipeline import reconstruct
    from services.core.session_reconstruction import SessionReconstruction
    from services.core.simulation.scenarios import simulate
    from services.store.scan_folder import read_scan_folder

    scan = read_scan_folder(scan_name) if os.sep in scan_name else simulate(scan_name, 1)
    runs: list[Run] = []
    finishing = [False]
    cls = normal_equations.NormalSolver
    init, solve, finish = cls.__init__, cls.solve, SessionReconstruction.finish

    def recording_init(solver: object) -> None:
        init(solver)  # type: ignore[arg-type]
        if finishing[0]:
            runs.append([])
            solver._run = runs[-1]  # type: ignore[attr-defined]

    def recording(solver: object, normal: object, rhs: np.ndarray) -> np.ndarray:
        if finishing[0] and hasattr(solver, "_run"):
            solver._run.append((normal.copy(), rhs.copy()))  # type: ignore[attr-defined]
        return solve(solver, normal, rhs)  # type: ignore[arg-type]

    def recorded_finish(session: SessionReconstruction) -> set[tuple[int, int]]:
        finishing[0] = True
        try:
            return finish(session)
        finally:
            finishing[0] = False

    cls.__init__, cls.solve = recording_init, recording  # type: ignore[method-assign]
    SessionReconstruction.finish = recorded_finish  # type: ignore[method-assign]
    try:
        reconstruct(scan, method_options("best"))
    finally:
        cls.__init__, cls.solve, SessionReconstruction.finish = init, solve, finish  # type: ignore[method-assign]
    return [run for run in runs if run]


def best_seconds(solve_run: object, run: Run, repeat: int) -> tuple[float, list[np.ndarray]]:
    """Return the best wall seconds of `repeat` passes of `solve_run` over a run, and its solutions."""
    best, xs = float("inf"), []
    for _ in range(repeat):
        started = time.perf_counter()
        xs = solve_run(run)  # type: ignore[operator]
        best = min(best, time.perf_counter() - started)
    return best, xs


def main() -> int:
    """Print the table: per scan, the finish's solves timed with the three solvers."""
    from scipy.sparse.linalg import spsolve

    from services.core.normal_equations import NormalSolver, solve_normal

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scan", action="append", default=None, help="a simulated scenario or a scan folder")
    p.add_argument("--repeat", type=int, default=3, help="passes per run of systems (the best is kept)")
    args = p.parse_args()
    scans = args.scan or ["raster"]

    def each(solver: object) -> object:
        return lambda run: [solver(normal, rhs) for normal, rhs in run]  # type: ignore[operator]

    def reusing(run: Run) -> list[np.ndarray]:
        solver = NormalSolver()
        return [solver.solve(normal, rhs) for normal, rhs in run]  # type: ignore[arg-type]

    print("the finish's pose-graph solves: spsolve (COLAMD, the baseline), solve_normal (symmetric mode) on each,")
    print("NormalSolver through each optimisation (its first system factored, the next on that factor)\n")
    print(
        "| scan | optimisations | solves | unknowns | spsolve ms | solve_normal ms | ratio | NormalSolver ms | ratio "
        "| factored | max difference (solve_normal / NormalSolver) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in scans:
        runs = finish_runs(name)
        times = [0.0, 0.0, 0.0]
        diffs = [0.0, 0.0]
        factored = 0
        for run in runs:
            t0, x0 = best_seconds(each(spsolve), run, args.repeat)
            t1, x1 = best_seconds(each(solve_normal), run, args.repeat)
            t2, x2 = best_seconds(reusing, run, args.repeat)
            times = [times[0] + t0, times[1] + t1, times[2] + t2]
            for k, xs in enumerate((x1, x2)):
                diffs[k] = max(diffs[k], *(float(np.max(np.abs(a - b))) for a, b in zip(xs, x0, strict=True)))
            counter = NormalSolver()
            for normal, rhs in run:
                counter.solve(normal, rhs)  # type: ignore[arg-type]
            factored += counter.factored
        solves = sum(len(run) for run in runs)
        shape = runs[0][0][0].shape[0] if runs else 0  # type: ignore[attr-defined]
        label = Path(name).name if os.sep in name else name
        base = max(times[0], 1e-12)
        print(
            f"| {label} | {len(runs)} | {solves} | {shape} | {1000 * times[0]:.0f} | {1000 * times[1]:.0f} | "
            f"{base / max(times[1], 1e-12):.2f}x | {1000 * times[2]:.0f} | {base / max(times[2], 1e-12):.2f}x | "
            f"{factored} | {diffs[0]:.1e} / {diffs[1]:.1e} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
