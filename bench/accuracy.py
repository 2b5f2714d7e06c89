"""Accuracy benchmark that one simulator cannot fool: the shared reference scans plus a robustness matrix.

(a) Every scan folder with a reference.csv under --shared (default ../shared/scans): real-looking NIR scans
    not made by this project's simulator. Their rows are marked `shared` in the table.
(b) A robustness matrix of the project's realistic simulator: each scenario in its default look, then one
    knob at a time away from it — vessel contrast 2-10 % (faint), 3-15 %, 10-30 %; noise 1 and 4 DN; no blur
    and heavy blur; no gain drift and a strong one; 16-bit frames — over several seeds. Rows marked `sim`.

The `strokes` scenario is scanned as a clinician scans (services/core/simulation/strokes.py): lifts between rows,
frames taken in the air, an island, dropped frames, a skewed force clock; the shared clinical_veins_24 likewise.

Every (scan, method) prints: registered % (of the frames with a reference: those on the skin), RMSE mm (over the
registered frames only: read it with the registered %), final drift mm, error ratio %, s/frame (wall time of the
whole offline pipeline), and the worse axis's tilt RMS error in degrees where the reference has tilts (the shared
scans, the tissue-* cells), and where
the error lies (evaluation.GlobalError): the path's scale % (+ too large) and turn deg about frame 0, and the RMSE
left after that similarity (the path's shape), `lead mm`: its mean along each frame's direction of travel (+ ahead
of the reference: a skin drag not undone in full), and `air placed`: frames placed that the reference has no row for
(taken in the air: none should be), `tracked %`: placed frames tracked without features (best-track),
`closures`: the loop-closure edges of the final pose graph (rows tied to rows: a dragged skin breaks them),
`drag fit` on the drag cells: the share of the simulator's true drags that the fitted ones make up (1: in full), and
where the reference has yaws, `loop yaw bias deg` and `other yaw bias deg`: the mean of what the final graph's loop
closures, and its other edges, measure of the relative yaw minus the tracker's (evaluation.edge_yaw_bias): a bias
that hundreds of edges share is not averaged out and turns the path; `yaw z loop / other`: the SD of those errors in
units of the SD the pose graph weighs each edge's yaw with (the two kinds' ratio is what counts: the kind with the
larger pulls the yaws harder than its evidence warrants, against the other); `loop yaw bias, top third of loads`: the
loop closures' mean over those whose frames' mean load is in the top third (docs/accuracy.md, Known limits: the
shared raster's turn).
Cells tissue-linear, tissue-stiffening, tissue-power, tissue-toe, tissue-saturating: a patient as on the shared
scans (a hand's tilt, a tissue law of that shape with anisotropy: along the frame's x or y, or for saturating fixed
in the tissue at any angle while the probe yaws +-15 deg), not an imaging look. Cell drag: that patient (linear
law) with the skin dragged by friction under the sliding window (simulation/skin_drag.py: stick-slip, 0.1-0.25 mm
per N at the window's centre, fading to the rim), the reference at the skin's rest position.

--texture PHOTO: the simulated cells' veins are a photograph's dark vessels instead of the procedural network
(vein_texture.make_photo_world), e.g. a fundus photograph as issue 14's hidden "real retinal vessel texture"
raster; scikit-image's wheel carries one (`pip download --no-deps scikit-image`, then unzip
skimage/data/retina.jpg from it).

Usage: python bench/accuracy.py [--quick] [--methods best,sift-chain,paper] [--scenarios raster,revisit,hard]
       [--cells default,faint,...] [--seeds 1,2] [--shared DIR | --no-shared] [--texture PHOTO]
       [--unmodelled-radial R] [--json OUT]
`paper` costs about 1 s/frame: leave it out of --methods for a fast run. best-nodrag: best without the skin drag
model (fit_drag=false), to show what learning the drag is worth. best-track: best tracking frames on keyframes
(track_overlap=0.92), to show what it costs in accuracy and saves in time; best-track85 at 0.85, as bench/probes.py's
tracking rows run. best-noloopgate: best without the looser loop gate for the closures a dragged skin breaks
(loop_ransac_px=0). best-nodragpairs: the skin drag learned from the matches' inliers alone, not their pairs
within 1.25 RANSAC gates of the similarity (drag_pair_gate=0).
best-reselect: the drag's pairs and the undragged edges' chosen about the undragged skin (drag_reselect=true).
--unmodelled-radial R: the simulated strain grows by R towards the window's rim (25 mm) instead of the renderer's
0.05, a term spec §2 does not have; the shared scans show none (a radial term in the rectification is best at zero on
all three), so 0 renders the simulator's scans as those are (cells named .../radial0).
--quick: the shared scans and five cells of the 40-frame `short` scenario, seed 1 (a few minutes without `paper`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
from tqdm import tqdm

from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.outputs.evaluation import edge_yaw_bias, evaluate_angles, evaluate_path
from services.core.outputs.session_report import path_angles_deg
from services.core.pipeline import reconstruct
from services.core.simulation.renderer import TISSUE_LAWS
from services.core.simulation.scenarios import simulate
from services.core.simulation.variants import FAINT_CONTRAST, ImagingVariant, scenario_imaging
from services.store.scan_folder import read_scan_folder
from services.store.texture_photo import read_texture_photo

DEFAULT_SHARED = Path(__file__).resolve().parents[2] / "shared" / "scans"
DRAG_FIT_MIN_MM = 0.2  # frames the simulator drags by more than this count in the drag-fit share (drag_fit_share)
ALL_METHODS = ("best", "paper", "sift-chain")

# one knob at a time away from the scenario's own realistic look (see services/core/simulation/variants.py)
LOOKS: dict[str, Callable[[ImagingVariant], ImagingVariant]] = {
    "default": lambda v: v,
    "faint": lambda v: dataclasses.replace(v, vessel_contrast=FAINT_CONTRAST),
    "contrast3-15": lambda v: dataclasses.replace(v, vessel_contrast=(0.03, 0.15)),
    "contrast10-30": lambda v: dataclasses.replace(v, vessel_contrast=(0.10, 0.30)),
    "noise1": lambda v: dataclasses.replace(v, noise_dn=1.0),
    "noise4": lambda v: dataclasses.replace(v, noise_dn=4.0),
    "no-blur": lambda v: dataclasses.replace(v, blur_fraction=0.0),
    "heavy-blur": lambda v: dataclasses.replace(v, blur_fraction=0.8, blur_length_px=(4, 16)),
    "no-drift": lambda v: dataclasses.replace(v, gain_drift=0.0),
    "drift30": lambda v: dataclasses.replace(v, gain_drift=0.3),
    "16bit": lambda v: dataclasses.replace(v, bit_depth=16),
}
# a patient as on the shared scans: a hand's tilt and a tissue law of each shape (simulate(..., tissue=...))
TISSUE_CELLS = {f"tissue-{law}": law for law in TISSUE_LAWS}
# a method as `best` with one model left out, to show what it is worth on the same scans
ABLATIONS = {
    "best-nodrag": ("best", {"fit_drag": False}),
    "best-isodrag": ("best", {"drag_across_sigma_mm": 0.6}),  # the drag prior as wide across the travel as along
    "best-track": ("best", {"track_overlap": 0.92}),  # frames tracked without features on keyframes (issue 32)
    "best-track85": ("best", {"track_overlap": 0.85}),  # fewer keyframes: what bench/probes.py's tracking row runs
    "best-noloopgate": ("best", {"loop_ransac_px": 0.0}),  # no looser gate for the closures a dragged skin breaks
    "best-nodragpairs": ("best", {"drag_pair_gate": 0.0}),  # the drag learned from the matches' inliers alone
    "best-reselect": ("best", {"drag_reselect": True}),  # pairs chosen about the undragged skin (opt-in)
    "best-tissueaxis": ("best", {"tissue_axis": True}),  # the anisotropy's axis may be fixed in the tissue (opt-in)
    # closures gated about one similarity alone and the chain's scale left free (before issue 31's drag match)
    "best-nodragmatch": ("best", {"loop_drag_match": False, "chain_scale_band": 0.0}),
}
DRAG_CELLS = {"drag": "linear"}  # a patient (linear law, a hand's tilt) whose skin the sliding window drags
QUICK_LOOKS = ("default", "faint", "noise4", "heavy-blur", "16bit", *TISSUE_CELLS, *DRAG_CELLS)
QUICK_SCENARIOS = ("short",)
FULL_SCENARIOS = ("raster", "revisit", "hard", "strokes")  # strokes: lifts, frames in the air, an island, drops


@dataclass(frozen=True)
class Cell:
    """One scan of the bench: a shared scan folder, or a simulated scenario in a look with a seed."""

    source: str  # "shared" or "sim"
    name: str
    folder: Path | None = None
    scenario: str = ""
    look: str = ""
    seed: int = 0
    texture: Path | None = None  # a photograph whose vessels are the simulated veins (None: procedural)
    radial: float | None = None  # the strain's growth to the rim the spec lacks (simulate's radial; None: default)

    def load(self) -> Scan:
        """Return the cell's Scan (read from its folder, or simulated)."""
        if self.folder is not None:
            return read_scan_folder(self.folder)
        photo = None if self.texture is None else read_texture_photo(self.texture)
        common: dict[str, Any] = {"texture": photo, "radial": self.radial}
        if self.look in TISSUE_CELLS:
            return simulate(self.scenario, self.seed, tissue=TISSUE_CELLS[self.look], **common)
        if self.look in DRAG_CELLS:
            return simulate(self.scenario, self.seed, tissue=DRAG_CELLS[self.look], drag=True, **common)
        imaging = LOOKS[self.look](scenario_imaging(self.scenario))
        return simulate(self.scenario, self.seed, dataclasses.replace(imaging, name=self.look), **common)


def shared_cells(root: Path) -> list[Cell]:
    """Return one Cell per folder under root that has a reference.csv (sorted by name)."""
    if not root.is_dir():
        return []
    return [
        Cell("shared", f"shared:{d.name}", folder=d) for d in sorted(root.iterdir()) if (d / "reference.csv").is_file()
    ]


def sim_cells(
    scenarios: list[str],
    looks: list[str],
    seeds: list[int],
    texture: Path | None = None,
    radial: float | None = None,
) -> list[Cell]:
    """Return the simulator's Cells: every scenario x look x seed (over a texture photograph's vessels if given;
    with the renderer's radial term replaced if radial is given)."""
    unknown = [lk for lk in looks if lk not in LOOKS and lk not in TISSUE_CELLS and lk not in DRAG_CELLS]
    if unknown:
        raise SystemExit(f"unknown cells {unknown}; expected some of {', '.join([*LOOKS, *TISSUE_CELLS, *DRAG_CELLS])}")
    return [
        Cell(
            "sim",
            f"{sc}/{lk}/s{seed}" + ("/photo" if texture else "") + ("" if radial is None else f"/radial{radial:g}"),
            scenario=sc,
            look=lk,
            seed=seed,
            texture=texture,
            radial=radial,
        )
        for sc in scenarios
        for lk in looks
        for seed in seeds
    ]


def run_one(cell: Cell, scan: Scan, method: str, bar: tqdm) -> dict[str, Any]:
    """Return one result row (JSON-able; mm, %, s) of a method on a loaded scan."""
    row: dict[str, Any] = {"source": cell.source, "cell": cell.name, "method": method, "frames": len(scan)}
    if cell.source == "sim":
        row.update(scenario=cell.scenario, look=cell.look, seed=cell.seed, imaging=scan.truth.get("imaging"))
    bar.reset(total=len(scan))
    bar.set_description(f"{cell.name} {method}")
    try:
        base, overrides = ABLATIONS.get(method, (method, {}))
        options = method_options(base).with_overrides(overrides)
        recon = reconstruct(scan, options, progress=lambda done, _total: bar.update(done - bar.n))
        report = evaluate_path(recon.estimate_mm, recon.registered, scan.by_seq(scan.reference_mm))
    except Exception as exc:  # a bench reports a crash as a row and carries on with the other cells
        row["error"] = f"{type(exc).__name__}: {exc}"
        return row
    row.update(
        registered_pct=100.0 * report.registered_fraction,
        rmse_mm=report.rmse_mm,
        max_error_mm=report.max_error_mm,
        final_drift_mm=report.final_drift_mm,
        error_ratio_pct=report.error_ratio_pct,
        path_length_mm=report.path_length_mm,
        s_per_frame=recon.seconds / len(scan),
        air_placed=report.n_registered_without_reference,  # frames placed that the reference says were in the air
        tracked_pct=100.0 * (1.0 - recon.keyframes / max(1, len(recon.poses))),  # placed without features
        closures=recon.closures,
    )
    if report.global_error is not None:  # where the error lies: the path's scale and turn, and its shape
        row.update(
            scale_pct=report.global_error.scale_pct,
            turn_deg=report.global_error.turn_deg,
            after_similarity_mm=report.global_error.after_similarity_mm,
            lead_mm=report.global_error.lead_mm,
        )
    if "drag_mm" in scan.truth:  # the simulator's skin drag: how much of it the fit finds
        row["drag_fit"] = drag_fit_share(recon.rows, scan)
    if scan.reference_angles_deg is not None:
        angles = evaluate_angles(path_angles_deg(recon.rows), recon.registered, scan.by_seq(scan.reference_angles_deg))
        row["tilt_rmse_deg"] = max(angles.get("tilt_x_rmse_deg", math.nan), angles.get("tilt_y_rmse_deg", math.nan))
        yaws = edge_yaw_bias(recon.edge_yaws, scan.by_seq(scan.reference_angles_deg)[:, 0])
        keys = (
            "loop_yaw_bias_deg",
            "other_yaw_bias_deg",
            "loop_yaw_z_sd",
            "other_yaw_z_sd",
            "loop_yaw_bias_high_load_deg",
        )
        row.update({k: yaws[k] for k in keys if k in yaws})
    return row


def drag_fit_share(rows: list[Any], scan: Scan) -> float:
    """Return the share of the simulator's true drags (each frame's, its axes) that the fitted ones (path.csv's,
    the path's axes, turned by the frame's yaw into its own) make up: the least-squares ratio over the placed frames
    dragged by more than DRAG_FIT_MIN_MM (1: the drag found in full; NaN without such frames)."""
    drags = np.asarray(scan.truth["drag_mm"], np.float64)  # per simulated frame: dropped seqs' too (strokes)
    true = drags if len(drags) == scan.n_seqs else scan.by_seq(drags)
    assert true is not None
    fit = np.full(len(true), np.nan, complex)
    for r in rows:
        if r.seq < len(fit) and r.status == "ok":
            fit[r.seq] = complex(r.drag_x_mm, r.drag_y_mm) * np.exp(-1j * np.radians(r.yaw_deg))
    t = true[:, 0] + 1j * true[:, 1]
    use = np.isfinite(fit) & np.isfinite(t) & (np.abs(t) > DRAG_FIT_MIN_MM)
    if not np.any(use):
        return math.nan
    return float((np.vdot(t[use], fit[use]) / np.vdot(t[use], t[use])).real)


HEADER = (
    f"{'source':<6} | {'scan / cell':<28} | {'method':<13} | {'registered %':>12} | {'RMSE mm':>8} |"
    f" {'final drift mm':>14} | {'error ratio %':>13} | {'s/frame':>7} | {'tilt RMS deg':>12} |"
    f" {'scale %':>7} | {'turn deg':>8} | {'after sim. mm':>13} | {'lead mm':>7} | {'air placed':>10} |"
    f" {'tracked %':>9} | {'closures':>8} | {'drag fit':>8} | {'loop yaw bias deg':>17} | {'other yaw bias deg':>18} |"
    f" {'yaw z loop / other':>18} | {'loop yaw bias, top third of loads':>33}"
)


def fmt(v: Any, spec: str) -> str:
    """Return v formatted with spec, or 'n/a' for None / NaN."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return format(v, spec)


def table_line(row: dict[str, Any]) -> str:
    """Return one table line of a result row."""
    head = f"{row['source']:<6} | {row['cell']:<28} | {row['method']:<13} |"
    if "error" in row:
        return f"{head} FAILED: {row['error']}"
    return (
        f"{head} {fmt(row['registered_pct'], '12.1f')} | {fmt(row['rmse_mm'], '8.3f')} |"
        f" {fmt(row['final_drift_mm'], '14.3f')} | {fmt(row['error_ratio_pct'], '13.4f')} |"
        f" {fmt(row['s_per_frame'], '7.3f')} | {fmt(row.get('tilt_rmse_deg'), '12.2f')} |"
        f" {fmt(row.get('scale_pct'), '+7.2f')} | {fmt(row.get('turn_deg'), '+8.3f')} |"
        f" {fmt(row.get('after_similarity_mm'), '13.3f')} | {fmt(row.get('lead_mm'), '+7.3f')} |"
        f" {fmt(row.get('air_placed'), '10d')} | {fmt(row.get('tracked_pct'), '9.1f')} |"
        f" {fmt(row.get('closures'), '8d')} | {fmt(row.get('drag_fit'), '8.2f')} |"
        f" {fmt(row.get('loop_yaw_bias_deg'), '+17.4f')} | {fmt(row.get('other_yaw_bias_deg'), '+18.4f')} |"
        f" {fmt(row.get('loop_yaw_z_sd'), '8.2f')} / {fmt(row.get('other_yaw_z_sd'), '7.2f')} |"
        f" {fmt(row.get('loop_yaw_bias_high_load_deg'), '+33.4f')}"
    )


def summary(rows: list[dict[str, Any]], methods: list[str]) -> list[str]:
    """Return summary lines per (source, method): cells run, mean registered %, median RMSE, cells >= 99 %."""
    lines = []
    for source in ("shared", "sim"):
        for method in methods:
            ok = [r for r in rows if r["source"] == source and r["method"] == method and "error" not in r]
            failed = sum(1 for r in rows if r["source"] == source and r["method"] == method and "error" in r)
            if not ok and not failed:
                continue
            reg = sorted(r["registered_pct"] for r in ok)
            rmse = sorted(r["rmse_mm"] for r in ok)
            median = rmse[len(rmse) // 2] if rmse else float("nan")
            full = sum(1 for v in reg if v >= 99.0)
            mean_reg = sum(reg) / len(reg) if reg else float("nan")
            lines.append(
                f"{source:<6} {method:<10} {len(ok)} cells ({failed} crashed): mean registered {mean_reg:.1f} %,"
                f" median RMSE {median:.3f} mm, {full}/{len(ok)} cells with >= 99 % registered"
            )
    return lines


def jsonable(value: Any) -> Any:
    """Return value with NaN / inf floats replaced by None (strict JSON), recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    return value


def main() -> int:
    """Run the benchmark, print the table and the summary, optionally dump JSON; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default=",".join(ALL_METHODS), help="comma list (paper is ~1 s/frame)")
    parser.add_argument("--scenarios", default=None, help=f"simulated scenarios (default {','.join(FULL_SCENARIOS)})")
    parser.add_argument("--cells", default=None, help=f"looks, some of {','.join(LOOKS)} (default all)")
    parser.add_argument("--seeds", default=None, help="comma list of seeds (default 1,2; --quick 1)")
    parser.add_argument("--quick", action="store_true", help="shared scans + 5 cells of the short scenario, seed 1")
    parser.add_argument("--shared", type=Path, default=DEFAULT_SHARED, help="folder of reference scans")
    parser.add_argument("--no-shared", action="store_true", help="skip the shared scans")
    parser.add_argument("--no-sim", action="store_true", help="skip the simulated matrix")
    parser.add_argument("--texture", type=Path, default=None, help="a photograph whose vessels are the sim's veins")
    parser.add_argument(
        "--unmodelled-radial",
        type=float,
        default=None,
        help="the simulated strain's growth to the window's rim (default 0.05; 0: none, as on the shared scans)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write every result row to this JSON file")
    args = parser.parse_args()

    methods = [m for m in args.methods.split(",") if m]
    bad = [m for m in methods if m not in ALL_METHODS and m not in ABLATIONS]
    if bad:
        parser.error(f"unknown methods {bad}; expected some of {', '.join([*ALL_METHODS, *ABLATIONS])}")
    scenarios = args.scenarios.split(",") if args.scenarios else list(QUICK_SCENARIOS if args.quick else FULL_SCENARIOS)
    looks = args.cells.split(",") if args.cells else list(QUICK_LOOKS if args.quick else LOOKS)
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else ([1] if args.quick else [1, 2])

    cells = [] if args.no_shared else shared_cells(args.shared)
    if not args.no_shared and not cells:
        print(f"note: no shared scans with reference.csv under {args.shared}", file=sys.stderr)
    if args.texture is not None:
        try:
            read_texture_photo(args.texture)  # a wrong path fails now, not after the shared scans' runs
        except ValueError as exc:
            parser.error(str(exc))
    if not args.no_sim:
        cells += sim_cells(scenarios, looks, seeds, args.texture, args.unmodelled_radial)

    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    runs = tqdm(total=len(cells) * len(methods), desc="runs", position=0, unit="run")
    frames_bar = tqdm(total=0, position=1, unit="frame", leave=False)
    tqdm.write(
        "rows marked 'shared' are the reference scans of ../shared/scans; 'sim' rows are this project's simulator"
    )
    tqdm.write(HEADER)
    tqdm.write("-" * len(HEADER))
    for cell in cells:
        frames_bar.set_description(f"loading {cell.name}")
        scan = cell.load()
        for method in methods:
            row = run_one(cell, scan, method, frames_bar)
            rows.append(row)
            tqdm.write(table_line(row))
            runs.update(1)
    frames_bar.close()
    runs.close()
    print()
    for line in summary(rows, methods):
        print(line)
    print(f"\n{len(rows)} runs in {time.perf_counter() - started:.0f} s on {os.cpu_count()} CPUs")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(jsonable(rows), indent=2, allow_nan=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
