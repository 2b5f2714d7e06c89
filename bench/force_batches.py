"""What merging a session's force batches costs per prepared frame as the session grows (issue 15).

    .venv/bin/python bench/force_batches.py [--batches 2400] [--rows 10] [--repeat 5]

A real SessionStore on a temporary data dir: one session receives --batches batches of --rows samples (one per
frame of a 10 frames/s probe). At every 400 batches it times, per call, what the prepare stage runs for each
frame: SessionStore.merged_forces after one new batch (incremental: only the new batch is merged), against the
baseline in the same run, a glob of every batch file and a merge of all of them (what merged_forces did before,
with the same per-file parse cache); merged_forces asked to cover a frame's time 1 s before the newest sample (a
frame prepared behind its upload, as the prepare stage asks: what was merged already serves, nothing is listed);
and an upload's put_forces (a re-send is found by its digest's marker, the batches not listed).
Prints a table of milliseconds (median of --repeat calls) and the baseline / incremental ratio.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.core.simulation.scenarios import nominal_calibration
from services.store.storage import SessionStore, _merge_rows


def _ms(call: Callable[[], object], repeat: int) -> float:
    """Return the median wall milliseconds of `repeat` calls."""
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        call()
        times.append((time.perf_counter() - started) * 1000.0)
    return statistics.median(times)


def main() -> int:
    """Grow one session's batches and print the merge cost per frame; return 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batches", type=int, default=2400, help="force batches of the session (one per frame)")
    p.add_argument("--rows", type=int, default=10, help="samples per batch (100 Hz sensors, 10 frames/s)")
    p.add_argument("--repeat", type=int, default=5, help="calls timed per point (median)")
    args = p.parse_args()
    store = SessionStore(Path(tempfile.mkdtemp(prefix="vm-batches-")))
    sid = store.create_session("b" * 64, "bench", nominal_calibration()).id
    bdir = store.session_dir(sid) / "raw" / "forces"

    def glob_and_merge_all() -> object:  # the baseline: every batch listed by a glob and merged, per frame
        return _merge_rows([store._load_batch(f, "samples", 5) for f in sorted(bdir.glob("[0-9]*.json"))], 5)

    head = ["batches", "merged_forces ms (one new batch)", "glob + merge all ms (before)", "ratio"]
    print("| " + " | ".join([*head, "covering a frame ms", "put_forces ms"]) + " |")
    print("|---:|---:|---:|---:|---:|---:|")
    t = 0.0

    def next_batch() -> list[list[float]]:
        nonlocal t
        rows = [[t + 0.01 * k, 1.0, 2.0, 3.0, 4.0] for k in range(args.rows)]
        t += 0.01 * args.rows
        return rows

    n = 0
    while n < args.batches:
        store.put_forces(sid, next_batch())
        store.merged_forces(sid)  # as the prepare stage does for each frame
        n += 1
        if n % 400 == 0 or n == args.batches:
            puts, merges = [], []
            for _ in range(args.repeat):  # each timed merge takes one new batch in, as a frame's preparation does
                batch = next_batch()
                puts.append(_ms(lambda b=batch: store.put_forces(sid, b), 1))
                merges.append(_ms(lambda: store.merged_forces(sid), 1))
                n += 1
            merged, put = statistics.median(merges), statistics.median(puts)
            base = _ms(glob_and_merge_all, args.repeat)
            store.put_forces(sid, next_batch())  # a batch newer than the frame: not needed to prepare it
            covering = _ms(lambda: store.merged_forces(sid, covering_t_s=t - 1.0), args.repeat)
            n += 1
            row = f"| {n} | {merged:.2f} | {base:.2f} | {base / merged:.1f}x | {covering:.3f} | {put:.2f} |"
            print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
