"""A finish computed ahead (issue 32): how many frames would move from where a finish run k frames before the end puts
them, to where the real finish does?

    .venv/bin/python bench/finish_ahead.py [--scan raster] [--scan exam] [--scan ../shared/scans/clinical_veins_24]
                                           [--ahead 10,30,100] [--every N]

The finish (SessionReconstruction.finish: the final pass with the skin's drag learned, the path held to the law's
scales, the gauge) moves nearly every frame of a `best` session by a quarter pixel or more from its live place
(`bench/finish.py`'s second table), so a live session pastes nearly every frame again at its end: 6 s of a 4-minute
examination's 9 s. If a live worker ran the finish's steps on a copy of its state from time to time while the scan
goes on, and kept the canvas pasted at those places, its real finish would paste again only the frames that moved
since. This measures what that would leave: the scan reconstructed in order, k frames before its end the places
the finish would give then (SessionReconstruction.places_if_finished: the finish run on a copy of the session's
state, the session left as it was), against the places of its real finish; the frames then placed whose place moves
by FINISH_MOVED_PX or more (SessionReconstruction.moved_px: the farthest corner plus the undone drag's change), their
median and 90th percentile move in mosaic px, and the frames placed since, which the finish pastes in any case.
With --every N, a second table: runs ahead every N frames through the scan (as a live worker with
finish_ahead_every_s does), and between each two runs the frames the later one moves by FINISH_MOVED_PX or more
from where the earlier one put them, as they are and after the one scale and shift of the canvas that fits the move
best (bench/finish.py's step_moves: what the compliance gauge's change between the runs accounts for, which
mosaic.json's px_per_mm and origin_px could carry without a frame pasted again); medians over the run pairs, with
their range. A --scan is a simulated scenario's name (seed 1) or a scan folder. Counts only: run beside other work,
it gives the same counts (a 2400-frame examination takes a few minutes); the first table's last column, each run
ahead's CPU seconds, is the machine's.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


Row = tuple[int, int, float, float, int, float]  # placed then, moved, median px, 90 % px, placed since, CPU s
Pair = tuple[int, int, int]  # frames placed at the earlier run, moved by the later one, ... after one scale and shift


def runs_ahead(scan_name: str, ahead: list[int], every: int) -> tuple[int, dict[int, Row], list[Pair]]:
    """Return, from one replay of the scan in order: its frame count; per k in `ahead`, the frames placed k frames
    before the end, how many of them the whole scan's finish moves by FINISH_MOVED_PX or more from where the finish
    then put them, the median and 90th percentile of those moves (mosaic px), the frames placed since (pasted at the
    end in any case) and the CPU seconds the run ahead took; and with `every` > 0, for each two runs ahead that many
    frames apart, the frames placed at the earlier run and how many of them the later one moves by FINISH_MOVED_PX
    or more, as they are and after the one scale and shift of the canvas that fits the move best."""
    import numpy as np

    from bench.finish import step_moves
    from services.core.methods import method_options
    from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
    from services.core.session_reconstruction import FINISH_MOVED_PX, SessionReconstruction
    from services.core.simulation.scenarios import simulate
    from services.store.scan_folder import read_scan_folder

    scan = read_scan_folder(scan_name) if os.sep in scan_name else simulate(scan_name, 1)
    options = method_options("best")
    mask, flat = window_setup(scan, options)
    recon = SessionReconstruction(scan.calibration, options, window_radius_mm(mask, scan.calibration))
    marks = {len(scan) - k: k for k in ahead}
    places, cpu_s, pairs, previous = {}, {}, [], None
    for n, pf in enumerate(prepared_frames(scan, frame_forces(scan), mask, flat, options)):
        if n in marks:  # the finish run ahead on a copy of the session's state, the session left as it was
            started = time.process_time()
            places[marks[n]] = recon.places_if_finished()
            cpu_s[marks[n]] = time.process_time() - started
        recon.add_next(pf)  # seqs the camera dropped recorded lost first
        if every and n % every == every - 1:
            run = recon.places_if_finished()
            if previous is not None:
                moved, _ = step_moves(recon, previous, run)
                similar, _ = step_moves(recon, previous, run, similar=True)
                pairs.append((len(previous), moved, similar))
            previous = run
    recon.finish()
    final = recon.stitch_places()
    rows = {}
    for k in ahead:
        before = places[k]
        kept = [i for i in final if i in before]
        moved = np.array([recon.moved_px(before[i], final[i]) for i in kept])
        median, p90 = np.percentile(moved, [50, 90])
        moved_n = int(np.count_nonzero(moved >= FINISH_MOVED_PX))
        rows[k] = (len(kept), moved_n, median, p90, len(final) - len(kept), cpu_s[k])
    return len(scan), rows, pairs


def main() -> int:
    """Print, per scan and k, how many frames a finish run k frames ahead would leave to paste again at the end."""
    import numpy as np

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scan", action="append", default=None, help="a simulated scenario or a scan folder")
    p.add_argument("--ahead", default="10,30,100", help="comma list of k: frames before the end")
    p.add_argument("--every", type=int, default=0, help="also compare runs ahead every N frames (second table)")
    args = p.parse_args()
    ahead = [int(k) for k in args.ahead.split(",")]
    print("a finish run k frames before the end, against the real one: of the frames then placed, those the real")
    print("finish moves by a quarter pixel or more (median and 90th percentile move, mosaic px); frames placed since\n")
    head = ["scan", "frames", "k", "placed then", "moved >= 0.25 px", "median px", "90 % px", "placed since"]
    print("| " + " | ".join([*head, "to paste at the end", "run ahead CPU s"]) + " |")
    print("|---|" + "---:|" * (len(head) + 1))
    every_rows = []
    for scan in args.scan or ["raster"]:
        name = str(Path(scan).resolve()) if os.sep in scan else scan
        n, rows, pairs = runs_ahead(name, ahead, args.every)
        for k, (placed, moved, median, p90, since, cpu) in rows.items():
            cells = f"{placed} | {moved} | {median:.2f} | {p90:.2f} | {since} | {moved + since} | {cpu:.2f}"
            print(f"| {Path(scan).name} | {n} | {k} | {cells} |", flush=True)
        if pairs:
            got = np.array(pairs)
            cells = " | ".join(f"{np.median(got[:, c]):.0f} ({got[:, c].min()}-{got[:, c].max()})" for c in range(3))
            every_rows.append(f"| {Path(scan).name} | {len(pairs)} | {cells} |")
    if args.every:
        print(f"\nruns ahead every {args.every} frames: of the frames placed at a run, those the next run moves by a")
        print("quarter pixel or more, as they are and after the one scale and shift of the canvas that fits the move")
        print("(median over the run pairs, range in brackets)\n")
        print("| scan | run pairs | frames placed at a run | moved >= 0.25 px | after one scale and shift |")
        print("|---|---:|---:|---:|---:|")
        print("\n".join(every_rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
