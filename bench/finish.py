"""The finish of a live session (issue 32): from its last frame registered to done, by part, per source tree.

    .venv/bin/python bench/finish.py [--scan raster] [--scan /work/scans/clinical_veins_24] [--frames N]
                                     [--repo PATH ...] [--repeat N] [--ahead-every N]

Each measurement runs in a child process as a live worker holds a session: every frame prepared and stored as its
prepared file (services.store), added in order to a live SessionReconstruction whose pixels are read back from
those files, with a live flush's tile work every 5 frames (pyramid, tiles written without fsync). Then it times
what the completion does (workers/stages/register/completion.py): the reconstruction's finish (final refinement,
self-calibration, the restitch), then the final flush's pyramid update, the tiles written durably through the
publisher and the whole images with the raw layers, written beside the tiles on a thread as a flush does
(Publisher.write_tiles_and_images: the images column is then 0 s of wall time, their CPU seconds in brackets; a tree
without it writes them after the tiles). Wall seconds (the session waits for them) and the process's CPU seconds.
The stitched column counts the frames the mosaic is made of (a frame over skin enough stitched frames show is placed,
not stitched: MethodOptions.stitch_cover_cap). A --scan is a simulated scenario's name (seed 1) or a scan folder.
The first --repo (default: this tree) is the baseline of the ratio column; another tree is e.g.
`git archive <commit> | tar -x -C /tmp/old`.
Last, a whole restitch (every frame pasted again on an empty canvas, as the finish does when every frame moved) is
timed RESTITCH_REPEATS times in the same process, its median in the last column: steadier than one finish's
restitch when comparing trees. --repeat N measures each tree N times, the trees taking turns, and prints each
figure's median (a busy or slow machine moves one run's restitch by a fifth). --ahead-every N runs the finish ahead
on a copy every N frames as a caught-up live worker does (SessionReconstruction.run_ahead; at 10 frames/s the
worker's finish_ahead_every_s 10 is N = 100), the canvas kept at its places: the finish then pastes again only what
moved since.
A second table says what moves the frames at the finish, step by step (SessionReconstruction.finish's `observe`):
how many frames the final pass (with the skin's drag learned and undone), the path held to the law's scales, and the
gauge (a scale about frame 0's rest centre) each move by FINISH_MOVED_PX or more on their own: what decides how many
frames the restitch pastes again.
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
from types import SimpleNamespace
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PARTS = ("finish", "pyramid", "tiles", "images")
RESTITCH_REPEATS = 3  # whole restitches timed after the finish (the median)
STEPS = ("refine", "scales", "calibrate")  # SessionReconstruction.finish's steps, as it names them to `observe`


class _Counters:
    """Stands in for Redis where the publisher counts tile renders (the bench measures files, not Redis)."""

    def hincrby(self, *_: object) -> None:
        """Count nothing."""

    def hincrbyfloat(self, *_: object) -> None:
        """Count nothing."""


def measure(scan_name: str, frames: int, flush_every: int, ahead_every: int = 0) -> dict[str, float | int]:
    """Return the wall and CPU seconds of a live session's finish and final flush, by part (this process)."""
    import cv2
    import numpy as np

    from services.core.methods import method_options
    from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
    from services.core.pipeline import frame_forces, prepared_frames, window_radius_mm, window_setup
    from services.core.session_reconstruction import SessionReconstruction
    from services.core.simulation.scenarios import simulate
    from services.store.results_store import ResultsStore
    from services.store.scan_folder import read_scan_folder
    from workers.publisher import Publisher

    cv2.setNumThreads(1)  # as a worker (worker_cv_threads)
    scan = read_scan_folder(scan_name) if os.sep in scan_name else simulate(scan_name, 1)
    options = method_options("best")
    calib = scan.calibration
    mask, flat = window_setup(scan, options)
    with tempfile.TemporaryDirectory(prefix="vm-finish-", ignore_cleanup_errors=True) as tmp:
        sid = uuid.uuid4().hex
        (Path(tmp) / "sessions" / sid).mkdir(parents=True)
        results = ResultsStore(Path(tmp))
        publisher = Publisher(SimpleNamespace(results=results, r=_Counters(), prefix="bench:"))  # type: ignore[arg-type]
        results.ensure_version(sid, 1, {"method": options.name})
        seqs: dict[int, int] = {}  # a frame's file is named by its seq; the reconstruction's index is its place
        for pf in prepared_frames(scan, frame_forces(scan), mask, flat, options):
            if pf.index >= frames:
                break
            results.write_prepared(sid, 1, pf)
            seqs[pf.index] = pf.seq
        n = len(seqs)

        def pixels(index: int) -> tuple[object, object]:
            return results.read_prepared_pixels(sid, 1, seqs[index])

        recon = SessionReconstruction(calib, options, window_radius_mm(mask, calib), live=True, pixels=pixels)
        pyramid = TilePyramid(DziGeometry.for_mosaic(calib.px_per_mm, 200.0))
        touched: set[tuple[int, int]] = set()
        revisions: dict[str, dict[str, int]] = {}
        started = time.monotonic()
        ahead_cpu, ahead_runs = 0.0, 0
        for k, i in enumerate(sorted(seqs)):
            pf = results.read_prepared(sid, 1, seqs[i])
            assert pf is not None
            for dropped in range(len(recon.results), i):  # seqs the camera dropped: missing, as live
                recon.lose(dropped)
            touched |= recon.add(pf)[1]
            if ahead_every and k % ahead_every == ahead_every - 1 and hasattr(recon, "run_ahead"):
                c0 = time.process_time()
                recon.run_ahead()  # as a caught-up worker every finish_ahead_every_s; its moved frames settle as added
                ahead_cpu, ahead_runs = ahead_cpu + time.process_time() - c0, ahead_runs + 1
            if k % flush_every == flush_every - 1:
                changed = pyramid.update(recon.canvas, touched)
                publisher.write_tiles(sid, 1, pyramid, changed, k, revisions, durable=False)
                touched = set()
        live_s = time.monotonic() - started
        pasted = dict(getattr(recon, "pasted", {}))
        out: dict[str, float | int] = {"frames": n, "live_s_per_frame": live_s / max(n, 1)}
        out.update(ahead_runs=ahead_runs, ahead_cpu=ahead_cpu)
        wall, cpu = time.monotonic, time.process_time
        t = (wall(), cpu())

        def lap(part: str) -> None:
            nonlocal t
            now = (wall(), cpu())
            out[part] = now[0] - t[0]
            out[part + "_cpu"] = now[1] - t[1]
            t = now

        places = {"live": recon.stitch_places()}  # where a restitch would paste each frame before the finish
        observing = [0.0, 0.0]  # the wall and CPU s spent here, taken off the finish's

        def observe(step: str) -> None:
            w0, c0 = wall(), cpu()
            places[step] = recon.stitch_places()
            observing[0] += wall() - w0
            observing[1] += cpu() - c0

        touched |= recon.finish(observe)
        lap("finish")
        out["finish"] -= observing[0]
        out["finish_cpu"] -= observing[1]
        for before, step in zip(("live", *STEPS), STEPS, strict=False):  # each step from the places before it
            moved, median = step_moves(recon, places[before], places[step])
            out[f"step_{step}_moved"], out[f"step_{step}_px"] = moved, median
        after_gauge = step_moves(recon, places["scales"], places["calibrate"], True)
        out["step_calibrate_after_scale_shift_moved"] = after_gauge[0]
        out["whole_after_scale_shift_moved"], out["whole_after_scale_shift_px"] = step_moves(
            recon, places["live"], places["calibrate"], True
        )
        changed = pyramid.update(recon.canvas, touched)
        lap("pyramid")
        if hasattr(publisher, "write_tiles_and_images"):  # the images written beside the tiles, as a flush does
            _, _, (_, images_cpu) = publisher.write_tiles_and_images(
                sid, 1, pyramid, changed, n, revisions, recon.canvas.render, raw_layers=True, durable=True
            )
            lap("tiles")
            lap("images")  # nothing left to wait for: their CPU moved here from the tiles' lap
            out["tiles_cpu"] -= images_cpu
            out["images_cpu"] = images_cpu
        else:  # a tree before: one after the other
            publisher.write_tiles(sid, 1, pyramid, changed, n, revisions, durable=True)
            lap("tiles")
            publisher.write_images(sid, 1, recon.canvas.render(), raw_layers=True)
            lap("images")
        out["tiles_written"] = len(changed)
        out["stitched"] = recon.stitched_count()  # the frames the mosaic is made of (stitch_cover leaves others out)
        out["pasted_again"] = sum(1 for i, a in recon.pasted.items() if i not in pasted or (a != pasted[i]).any())
        out["moved_px"], out["moved_after_affine_px"] = moves_px(recon, pasted)
        out.update({f"finish_{k}": v for k, v in getattr(recon, "finish_seconds", {}).items()})
        # the restitch's own cost, steadier than one finish's: every frame pasted again (pixels read back from its
        # file, planes built, warped, added) on an empty canvas, RESTITCH_REPEATS times, the median CPU and wall s
        runs = []
        for _ in range(RESTITCH_REPEATS):
            c0, w0 = cpu(), wall()
            recon.restitch()
            runs.append((cpu() - c0, wall() - w0))
        out["restitch_all_cpu"], out["restitch_all"] = (float(v) for v in np.median(np.array(runs), axis=0))
    return out


def moves_px(recon: Any, pasted: dict[int, Any]) -> tuple[float, float]:
    """Return the median move (mosaic px, the farthest corner) of the frames pasted live to their final places, and
    what is left of it after the best affine map of the whole canvas: whether one warp could stand for the restitch."""
    import numpy as np

    kept = [i for i in recon.pasted if i in pasted]
    if not kept:
        return float("nan"), float("nan")
    before = np.array([recon.corners_px(pasted[i]) for i in kept])
    after = np.array([recon.corners_px(recon.pasted[i]) for i in kept])
    moved = np.abs(after - before).max(axis=1)
    x = np.column_stack([before.real.ravel(), before.imag.ravel(), np.ones(before.size)])
    fitted = x @ np.linalg.lstsq(x, np.column_stack([after.real.ravel(), after.imag.ravel()]), rcond=None)[0]
    left = np.abs(fitted[:, 0] + 1j * fitted[:, 1] - after.ravel()).reshape(-1, 4).max(axis=1)
    return float(np.median(moved)), float(np.median(left))


def step_moves(recon: Any, before: dict[int, Any], after: dict[int, Any], similar: bool = False) -> tuple[int, float]:
    """Return how many frames one step of the finish moves by FINISH_MOVED_PX or more and their median move (mosaic
    px, the finish's own measure: SessionReconstruction.moved_px), from the places before to those after
    (SessionReconstruction.stitch_places). similar: first map `before` by the one scale and shift of the canvas that
    fits `after` best (no turn: what mosaic.json's px_per_mm and origin_px could carry without any frame pasted)."""
    import numpy as np

    from services.core.session_reconstruction import FINISH_MOVED_PX

    kept = [i for i in after if i in before]
    if not kept:
        return 0, float("nan")
    if similar:
        old = np.array([recon.corners_px(before[i][0]) for i in kept]).ravel()
        new = np.array([recon.corners_px(after[i][0]) for i in kept]).ravel()
        zero, one = np.zeros(old.size), np.ones(old.size)  # new = s old + o: a real scale s, a shift o (no turn)
        design = np.vstack([np.column_stack([old.real, one, zero]), np.column_stack([old.imag, zero, one])])
        s, ox, oy = np.linalg.lstsq(design, np.concatenate([new.real, new.imag]), rcond=None)[0]
        fitted, new = (s * old + (ox + 1j * oy)).reshape(-1, 4), new.reshape(-1, 4)
        drags = np.array([recon.drag_shift_px(before[i], after[i]) for i in kept])
        moved = np.abs(new - fitted).max(axis=1) + drags
    else:
        moved = np.array([recon.moved_px(before[i], after[i]) for i in kept])
    return int(np.count_nonzero(moved >= FINISH_MOVED_PX)), float(np.median(moved))


def median_of(runs: list[dict[str, float | int]]) -> dict[str, float | int]:
    """Return each figure's median over repeated measurements of one tree."""
    import numpy as np

    return {key: float(np.median([run[key] for run in runs])) for key in runs[0]}


def run_child(args: argparse.Namespace, scan: str, repo: Path) -> dict[str, float | int]:
    """Return one measurement made by a child process on source tree `repo`."""
    env = {**os.environ, "PYTHONPATH": str(repo), "OPENBLAS_NUM_THREADS": "1"}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--scan", scan, "--frames", str(args.frames)]
    cmd += ["--ahead-every", str(args.ahead_every)]
    done = subprocess.run(cmd, env=env, cwd=repo, stdout=subprocess.PIPE, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"a measurement failed (exit {done.returncode})")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    """Print the table of a live session's finish and final flush by part, per scan and source tree."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scan", action="append", default=None, help="a simulated scenario or a scan folder")
    p.add_argument("--frames", type=int, default=100000, help="the scan's first N frames")
    p.add_argument("--repo", type=Path, action="append", default=None, help="source trees to measure")
    p.add_argument("--repeat", type=int, default=1, help="measurements per tree (the trees taking turns): medians")
    p.add_argument("--ahead-every", type=int, default=0, help="run the finish ahead every N frames (run_ahead)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    # a scan folder named relative to here: the children run in their own trees
    scans = [str(Path(scan).resolve()) if os.sep in scan else scan for scan in args.scan or ["raster"]]
    if args.child:
        print(json.dumps(measure(scans[0], args.frames, flush_every=5, ahead_every=args.ahead_every)))
        return 0
    repos = args.repo or [REPO]
    print("a live session's finish and final flush; wall s (CPU s); frames pasted again at the finish, tiles written;")
    print("how far the finish moves a pasted frame (median, px), and what one affine map of the canvas leaves of it\n")
    head = ["scan", "tree", "frames", "stitched", *PARTS, "done after the last frame", "vs first", "pasted again"]
    head += ["tiles"]
    head += ["moved px", "after one affine", f"every frame pasted again (median of {RESTITCH_REPEATS})"]
    print("| " + " | ".join(head) + " |")
    print("|---|---|" + "---:|" * (len(head) - 2))
    steps: list[str] = []  # the second table's rows
    for scan in scans:
        base = None
        runs: dict[Path, list[dict[str, float | int]]] = {repo: [] for repo in repos}
        for _ in range(max(1, args.repeat)):
            for repo in repos:
                print(f"running {Path(scan).name} on {repo} ...", file=sys.stderr)
                runs[repo].append(run_child(args, scan, repo))
        for repo in repos:
            got = median_of(runs[repo])
            total = sum(float(got[part]) for part in PARTS)
            base = total if base is None else base
            cells = " | ".join(f"{got[part]:.2f} ({got[part + '_cpu']:.2f})" for part in PARTS)
            split = ", ".join(f"{k[7:]} {v:.2f}" for k, v in got.items() if k.startswith("finish_") and k[7:] != "cpu")
            name = repo.resolve().name  # "." names its folder
            print(
                f"| {Path(scan).name} | {name} | {got['frames']:.0f} | {got['stitched']:.0f} | {cells} | {total:.2f} "
                f"| {total / base:.2f}x "
                f"| {got['pasted_again']:.0f} | {got['tiles_written']:.0f} | {got['moved_px']:.2f} "
                f"| {got['moved_after_affine_px']:.2f} | {got['restitch_all']:.2f} ({got['restitch_all_cpu']:.2f}) |",
                flush=True,
            )
            if split:
                print(f"finish by part ({Path(scan).name}, {name}): {split}", file=sys.stderr)
            print(
                f"live ({Path(scan).name}, {name}): {1000 * got['live_s_per_frame']:.1f} ms a frame (wall); runs ahead "
                f"{got['ahead_runs']:.0f}, CPU {got['ahead_cpu']:.2f} s in all",
                file=sys.stderr,
            )
            steps.append(
                f"| {Path(scan).name} | {name} | {got['frames']:.0f} | "
                + " | ".join(f"{got[f'step_{k}_moved']:.0f} ({got[f'step_{k}_px']:.2f})" for k in STEPS)
                + f" | {got['step_calibrate_after_scale_shift_moved']:.0f}"
                + f" | {got['whole_after_scale_shift_moved']:.0f} ({got['whole_after_scale_shift_px']:.2f}) |"
            )
    print("\nwhat moves the frames at the finish: frames a step alone moves by a quarter pixel or more")
    print("(FINISH_MOVED_PX, the finish's own measure: the farthest corner plus the undone drag's change), the median")
    print("move in px in brackets; the last two columns: the gauge's step, and the whole finish, after the one scale")
    print("and shift of the canvas that fits each best (no turn: what mosaic.json could carry)\n")
    print(
        "| scan | tree | frames | the final pass, drag learned | the law's scales | the gauge "
        "| the gauge after a scale and shift | the whole finish after a scale and shift |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    print("\n".join(steps))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
