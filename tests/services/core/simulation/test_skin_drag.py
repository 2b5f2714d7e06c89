"""The simulated skin drag (services.core.simulation.skin_drag): stick-slip along the motion, a centre-to-rim
profile, the reference at the skin's rest position; and `best` learning it back from a scan with drag."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.methods import method_options
from services.core.outputs.evaluation import evaluate_path
from services.core.pipeline import Reconstruction, reconstruct
from services.core.simulation.probe_path import rotation
from services.core.simulation.scenarios import simulate
from services.core.simulation.skin_drag import GAIN_MM_PER_N, SkinDrag, dragged_rest_mm
from tests.tolerances import TOL


def test_profile_is_full_in_the_core_and_none_beyond_the_rim() -> None:
    drag = SkinDrag(0.15, 6.0, 30.0)
    phi = drag.profile(np.array([0.0, 6.0, 18.0, 30.0, 45.0]))
    assert np.allclose(phi, [1.0, 1.0, 0.5, 0.0, 0.0])
    rest = dragged_rest_mm(np.array([[0.0, 0.0], [40.0, 0.0]]), drag, np.array([1.0, -0.5]))
    assert np.allclose(rest, [[-1.0, 0.5], [40.0, 0.0]])  # the centre's skin rests behind it; the rim's does not move


def test_a_scan_with_drag_is_the_same_scan_with_its_skin_dragged() -> None:
    plain, dragged = simulate("short", 2), simulate("short", 2, drag=True)
    truth = dragged.truth
    drags = np.array(truth["drag_mm"])
    assert GAIN_MM_PER_N[0] <= truth["drag"]["gain_mm_per_n"] <= GAIN_MM_PER_N[1]
    assert np.array_equal(plain.forces_n, dragged.forces_n)  # the same motion, loads and streams
    assert 0.3 < np.median(np.hypot(*drags.T)) < 4.0  # mm at the centre: 0.1-0.25 mm/N at the scan's 4-18 N
    assert np.mean(np.abs(plain.frame(5).astype(float) - dragged.frame(5).astype(float))) > 0.5  # grey levels
    # the reference is where the skin under the centre rests: the probe's centre less its drag, turned to the world
    # (in frame 0's coordinates, from frame 0's rest position: yaw relative to frame 0's, which has yaw 0)
    yaw = np.array(plain.truth["poses"])[:, 2]
    moved = np.array(dragged.truth["poses"])[:, :2] - np.array(plain.truth["poses"])[:, :2]
    expected = -np.stack([rotation(float(a)) @ d for a, d in zip(yaw, drags, strict=True)]) + drags[0]
    assert np.allclose(moved, expected, atol=1e-6)


@pytest.mark.slow
def test_best_learns_the_drag_back() -> None:
    scan = simulate("short", 1, tissue="linear", drag=True)
    learned = reconstruct(scan, method_options("best"))
    ignored = reconstruct(scan, method_options("best").with_overrides({"fit_drag": False}))
    assert learned.learned["drag_kept"] and not ignored.learned.get("drag_kept")
    true_gain = scan.truth["drag"]["gain_mm_per_n"]
    assert 0.5 * true_gain < learned.learned["drag_gain_mm_per_n"] < 1.5 * true_gain  # stick-slip: a share of it
    rmse = [evaluate_path(r.estimate_mm, r.registered, scan.reference_mm).rmse_mm for r in (learned, ignored)]
    assert TOL.sim_short_drag_rmse_mm[0] <= rmse[0] <= TOL.sim_short_drag_rmse_mm[1], rmse
    assert rmse[0] < 0.9 * rmse[1], rmse  # learning the drag pays
    drag_x = np.array([row.drag_x_mm for row in learned.rows])
    assert np.all(np.isfinite(drag_x)) and np.median(np.abs(drag_x)) > 0.2  # reported per frame (path.csv)


def _dragged_raster(seed: int) -> tuple[Reconstruction, float]:
    """Return `best`'s reconstruction of the simulated dragged raster of a seed and its path RMSE (mm)."""
    scan = simulate("raster", seed, tissue="linear", drag=True)
    recon = reconstruct(scan, method_options("best"))
    return recon, evaluate_path(recon.estimate_mm, recon.registered, scan.reference_mm).rmse_mm


@pytest.mark.slow
def test_a_strong_drag_no_longer_breaks_a_raster() -> None:
    # rows dragged opposite ways: closures gated about the drag model (registration.drag_match), the chain's scale
    # held in its band while the scan goes on (MethodOptions.chain_scale_band)
    recon, rmse = _dragged_raster(3)
    assert TOL.sim_raster_strong_drag_rmse_mm[0] <= rmse <= TOL.sim_raster_strong_drag_rmse_mm[1], rmse
    assert recon.closures >= 40, recon.closures  # 66 measured; 9 when the drag broke them


@pytest.mark.slow
def test_a_dragged_raster_keeps_its_scale_while_the_scan_goes_on() -> None:
    # the edges' drag, undone only at the end, made every global pass shrink the map about frame 0 until frame 0's
    # own edges were dropped: the map's mean scale is held within chain_scale_band while the scan goes on
    recon, rmse = _dragged_raster(4)
    assert TOL.sim_raster_drag_seed4_rmse_mm[0] <= rmse <= TOL.sim_raster_drag_seed4_rmse_mm[1], rmse
    assert recon.learned["gauge"] > 0.85, recon.learned["gauge"]  # 0.90 measured; 0.49 when the map shrank
