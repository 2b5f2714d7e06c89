"""Accuracy benchmark: simulate each scenario (fixed seeds), run every method, print one table.

Usage: python bench/accuracy.py [--scenarios raster,revisit,hard] [--methods sift-chain,paper,best]
       [--seed 1] [--out bench/out]
Also runs `best` without global refinement on every scenario (the refinement ablation), and writes one
comparison plot per scenario to --out.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.evaluation import evaluate_path
from services.methods import method_options
from services.pipeline import reconstruct
from services.plots import plot_method_comparison
from services.simulation.scenarios import simulate

ABLATION = "best-no-refine"


def run(scenarios: list[str], methods: list[str], seed: int, out: Path) -> list[dict[str, object]]:
    """Return one result row per (scenario, method), printing the table as it goes."""
    rows = []
    header = (
        f"{'scenario':<9}| {'method':<15}| {'registered %':>12} | {'RMSE mm':>8} | {'final drift mm':>14} |"
        f" {'error ratio %':>13} | {'s/frame':>7}"
    )
    print(header)
    print("-" * len(header))
    for scenario in scenarios:
        scan = simulate(scenario, seed)
        paths = {}
        for name in [*methods, ABLATION]:
            if name == ABLATION:
                if "best" not in methods:
                    continue
                options = method_options("best").with_overrides({"refine": False, "name": ABLATION})
            else:
                options = method_options(name)
            recon = reconstruct(scan, options)
            report = evaluate_path(recon.estimate_mm, recon.registered, scan.reference_mm)
            row = {
                "scenario": scenario,
                "method": name,
                "frames": len(scan),
                "registered_pct": 100 * report.registered_fraction,
                "rmse_mm": report.rmse_mm,
                "final_drift_mm": report.final_drift_mm,
                "error_ratio_pct": report.error_ratio_pct,
                "s_per_frame": recon.seconds / len(scan),
                "path_length_mm": report.path_length_mm,
            }
            rows.append(row)
            paths[name] = (recon.estimate_mm, recon.registered)
            print(
                f"{scenario:<9}| {name:<15}| {row['registered_pct']:>12.1f} | {report.rmse_mm:>8.3f} |"
                f" {report.final_drift_mm:>14.3f} | {report.error_ratio_pct:>13.4f} | {row['s_per_frame']:>7.3f}",
                flush=True,
            )
        plot_method_comparison(out / f"{scenario}_paths.png", paths, scan.reference_mm)
    return rows


def main() -> int:
    """Run the benchmark and write bench/out/accuracy.json; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenarios", default="raster,revisit,hard")
    parser.add_argument("--methods", default="sift-chain,paper,best")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "out")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows = run(args.scenarios.split(","), args.methods.split(","), args.seed, args.out)
    (args.out / "accuracy.json").write_text(json.dumps(rows, indent=2))
    print(f"\n{len(rows)} runs in {time.perf_counter() - started:.0f} s on {os.cpu_count()} CPUs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
