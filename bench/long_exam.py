"""Long examinations offline (issue 15): does the cost per frame and the memory stay flat as a scan grows?

    .venv/bin/python bench/long_exam.py [--frames 2400] [--baseline raster] [--seed 1] [--method best] [--keep DIR]

Simulates, in the same run, the baseline (a 336-frame raster) and an examination of --frames frames (passes
over one 168 x 108 mm area, ~3.6 mm per frame: 2400 frames are 4 minutes at 10 frames/s and ~8.7 m), writes
both as scan folders and reconstructs each with `veinmosaic reconstruct` in a fresh process, as an operator
would. Per scan it prints frames, path length, wall and CPU seconds per frame, peak resident memory of the
reconstructing process (ru_maxrss), placed frames and RMSE against the simulator's truth; and the exam's
ratios to the baseline. Targets (issue 15): CPU per frame <= 1.3x the baseline's, peak memory <= 1.5 GB.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.core.simulation.scenarios import simulate
from services.store.scan_folder import write_scan_folder

CPU_RATIO_TARGET = 1.3
PEAK_TARGET_MB = 1536.0
# The child reconstructs through the CLI and reports its own resource use (seconds, kB) on its last line.
CHILD = """
import json, resource, sys
from cli.main import main
rc = main(sys.argv[1:])
u = resource.getrusage(resource.RUSAGE_SELF)
print("RUSAGE " + json.dumps({"rc": rc, "cpu_s": u.ru_utime + u.ru_stime, "maxrss_kb": u.ru_maxrss}))
"""


def reconstruct(folder: Path, out: Path, method: str) -> dict[str, float]:
    """Return wall_s, cpu_s, peak_mb and the report's accuracy of `veinmosaic reconstruct` in a fresh process."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, "reconstruct", str(folder), "--out", str(out), "--method", method],
        capture_output=True,
        text=True,
        check=False,
    )
    wall = time.perf_counter() - t0
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RUSAGE ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"reconstruct failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    usage = json.loads(lines[-1][len("RUSAGE ") :])
    accuracy = json.loads((out / "report.json").read_text())  # the accuracy keys are top-level
    return {
        "wall_s": wall,
        "cpu_s": float(usage["cpu_s"]),
        "peak_mb": float(usage["maxrss_kb"]) / 1024.0,
        "rmse_mm": float(accuracy.get("rmse_mm", float("nan"))),
        "registered": float(accuracy.get("registered_fraction", float("nan"))),
    }


def main() -> int:
    """Run the baseline and the examination and print the table; return 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=2400, help="frames of the examination (10 per second)")
    p.add_argument("--baseline", default="raster", help="scenario of the baseline row (336 frames for raster)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--method", default="best")
    p.add_argument("--keep", type=Path, default=None, help="keep the scan and result folders here")
    args = p.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="vm-long-"))
    rows = []
    for name, make in (
        (args.baseline, lambda: simulate(args.baseline, args.seed)),
        (f"exam-{args.frames}", lambda: simulate("exam", args.seed, frames=args.frames)),
    ):
        folder = root / f"scan-{name}"
        if not (folder / "frames").is_dir():
            print(f"simulating {name} ...", flush=True)
            scan = make()
            write_scan_folder(scan, folder)
            length = scan.truth["path_length_mm"]
            del scan
        else:  # kept from an earlier run (--keep): the length from its truth
            length = float(json.loads((folder / "truth.json").read_text()).get("path_length_mm", float("nan")))
        n = len(list((folder / "frames").iterdir()))
        print(f"reconstructing {name} ({n} frames) ...", flush=True)
        res = reconstruct(folder, root / f"out-{name}", args.method)
        rows.append((name, n, length, res))
    base = rows[0][3]
    print()
    print(f"method {args.method}, seed {args.seed}; ratios against {rows[0][0]} in the same run")
    head = "| scan | frames | path m | wall s/frame | CPU s/frame | CPU/frame ratio | peak MB | placed | RMSE mm |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for name, n, length, r in rows:
        ratio = (r["cpu_s"] / n) / (base["cpu_s"] / rows[0][1])
        print(
            f"| {name} | {n} | {length / 1000:.2f} | {r['wall_s'] / n:.3f} | {r['cpu_s'] / n:.3f} | {ratio:.2f} "
            f"| {r['peak_mb']:.0f} | {100 * r['registered']:.1f} % | {r['rmse_mm']:.3f} |"
        )
    exam = rows[-1][3]
    ratio = (exam["cpu_s"] / rows[-1][1]) / (base["cpu_s"] / rows[0][1])
    print(
        f"\nCPU per frame {ratio:.2f}x the baseline's (target <= {CPU_RATIO_TARGET}); "
        f"peak {exam['peak_mb']:.0f} MB (target <= {PEAK_TARGET_MB:.0f}); folders in {root}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
