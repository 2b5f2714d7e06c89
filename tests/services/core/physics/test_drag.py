"""The skin drag model (services.core.physics.drag): synthetic matches between frames whose skin is dragged by known
amounts, the drags fitted back (also on pairs re-selected about the undragged skin), the edges undragged, and a scan
without drag left alone."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.core.methods import method_options
from services.core.physics.drag import (
    MAX_ALONG_TRAVEL_DEG,
    PRIOR_SIGMA_MM,
    RESELECT_ROUNDS,
    DragEvidence,
    DragFit,
    fit_drag,
    undrag,
    undrag_maps,
    undragged_transforms,
)
from services.core.similarity import Similarity, lsq_similarity
from tests.services.core.physics.dragged_serpentine import WIDTH_MM, dragged_serpentine, gated


def _at(s: Similarity, z: complex) -> complex:
    return s.a * z + s.t


def test_drags_are_found_where_the_skin_is_dragged() -> None:
    evidence, loads, directions, truth = dragged_serpentine(0.1, seed=3)  # 0.4-1.6 mm at the centre
    fit = fit_drag(evidence, loads, directions)
    assert fit is not None and fit.kept
    assert fit.width_mm == WIDTH_MM  # the profile's width chosen by the evidence
    found = np.array([fit.of(k) for k in truth["drags"]])
    true = np.array(list(truth["drags"].values()))
    # within 0.15 mm rms (true drags of 0.4-1.6 mm; a tenth of the 1.3 mm rms of the drags themselves) and
    # with the gain along the motion within 30 % of the truth's mean (0.1 x 0.8: stick-slip draws 0.6-1.0)
    assert np.sqrt(np.mean(np.abs(found - true) ** 2)) < 0.15
    assert 0.056 < fit.gain_mm_per_n.real < 0.104 and abs(fit.gain_mm_per_n.imag) < 0.01


def test_undragged_edges_match_the_rest_poses() -> None:
    evidence, loads, directions, truth = dragged_serpentine(0.1, seed=4)
    fit = fit_drag(evidence, loads, directions)
    assert fit is not None and fit.kept
    poses = truth["poses"]
    raw_err, fixed_err = [], []
    for ev in evidence:
        true_rel = poses[ev.i].inverse().compose(poses[ev.j])
        pj = ev.pairs[:, 0] + 1j * ev.pairs[:, 1]
        pi = ev.pairs[:, 2] + 1j * ev.pairs[:, 3]
        c = complex(pj.mean())  # where an edge's translation is measured (pose_graph.edge_centres_and_levers)
        measured = lsq_similarity(pj, pi)  # the match's least-squares similarity
        relative, _ = undragged_transforms(measured, [], ev.pairs, fit.of(ev.i), fit.of(ev.j), fit.width_mm)
        raw_err.append(abs(_at(measured, c) - _at(true_rel, c)))
        fixed_err.append(abs(_at(relative, c) - _at(true_rel, c)))
    # undragged, the relative poses are right within 0.05 mm rms at the pairs' centroid (noise 0.03 mm over 60
    # pairs, plus the fit's drag error); raw, the drags (up to 1.6 mm, flipping between rows) leave them off by more
    assert np.sqrt(np.mean(np.square(fixed_err))) < 0.05
    assert np.sqrt(np.mean(np.square(raw_err))) > 0.3  # measured 0.79


def test_no_drag_is_kept_where_there_is_none() -> None:
    evidence, loads, directions, _ = dragged_serpentine(0.0, seed=5)
    fit = fit_drag(evidence, loads, directions)
    assert fit is not None and not fit.kept
    assert all(fit.of(k) == 0 for k in loads)


def test_a_drag_across_the_strokes_is_not_kept() -> None:
    # the same skin deformation turned 90 deg from the travel: it explains the pairs as well, but a window's friction
    # drags along its stroke (a simulated hard scan without drag kept one at -100 deg, its path 1.34 -> 2.55 mm)
    evidence, loads, directions, _ = dragged_serpentine(0.1, seed=3, turn_deg=90.0)
    fit = fit_drag(evidence, loads, directions)
    assert fit is not None and fit.cost_with < 0.5 * fit.cost_without  # the model explains it ...
    assert abs(np.degrees(np.angle(fit.gain_mm_per_n))) > MAX_ALONG_TRAVEL_DEG and not fit.kept  # ... and drops it
    along = fit_drag(*dragged_serpentine(0.1, seed=3, turn_deg=30.0)[:3])
    assert along is not None and along.kept  # a drag 30 deg off the travel (a slanted stroke) is kept


def test_the_prior_holds_a_drag_along_the_travel_where_the_pairs_are_noisy() -> None:
    # drags along the travel seen through noisy pairs (0.1 mm, nearly a pixel): what the fit puts across the travel
    # is error. The prior tighter across (best's drag_across_sigma_mm, 0.3 mm) than along (PRIOR_SIGMA_MM, 0.6) takes
    # a quarter of it off (measured 0.148 -> 0.107 mm rms) and leaves the part along the travel as it was (0.053 mm)
    evidence, loads, directions, truth = dragged_serpentine(0.1, seed=3, noise_mm=0.1)
    best_sigma = method_options("best").drag_across_sigma_mm
    assert best_sigma < PRIOR_SIGMA_MM  # best holds the drag tighter across the travel than along it
    errors = {}
    for across_sigma in (PRIOR_SIGMA_MM, best_sigma):
        fit = fit_drag(evidence, loads, directions, across_sigma_mm=across_sigma)
        assert fit is not None and fit.kept
        # each drag's error in its frame's travel axes: along (real), across (imaginary)
        error = np.array([(fit.of(k) - true) * np.conj(directions[k]) for k, true in truth["drags"].items()])
        errors[across_sigma] = (np.sqrt(np.mean(error.real**2)), np.sqrt(np.mean(error.imag**2)))
    (along_iso, across_iso), (along, across) = errors[PRIOR_SIGMA_MM], errors[best_sigma]
    assert across < 0.8 * across_iso
    assert abs(along - along_iso) < 0.05 * along_iso


def test_too_little_evidence_fits_nothing() -> None:
    evidence, loads, directions, _ = dragged_serpentine(0.1, seed=6)
    assert fit_drag(evidence[:5], loads, directions) is None


@pytest.mark.parametrize("drag", [0j, 0.8 + 0.3j])
def test_undrag_moves_the_centre_most(drag: complex) -> None:
    points = np.array([0j, 10.0, 30j, 60.0])
    moved = points - undrag(points, drag, WIDTH_MM)
    assert np.allclose(moved[0], drag)  # the centre by the whole drag
    assert np.all(np.abs(moved[1:]) <= abs(moved[0]) + 1e-12) and abs(moved[-1]) < 0.01 * abs(drag) + 1e-12


def test_undrag_maps_restore_the_skin_at_rest() -> None:
    """A frame of a smooth pattern imaged under a 1.2 mm drag, resampled by undrag_maps, matches the frame at rest
    within 1 % of its range (the maps' first-order inverse plus bilinear interpolation); the dragged one does not."""
    h, w, px_per_mm, centre = 240, 320, 8.0, (159.5, 119.5)
    drag = 1.0 + 0.6j

    def skin(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:  # a smooth pattern at rest, 0..1
        return 0.5 + 0.25 * np.sin(x_mm / 1.7) + 0.25 * np.cos(y_mm / 2.3)

    gy, gx = np.mgrid[0:h, 0:w].astype(np.float64)
    p = (gx - centre[0]) / px_per_mm + 1j * (gy - centre[1]) / px_per_mm
    rest_of_p = undrag(p, drag, WIDTH_MM)  # the skin each pixel shows under the drag
    imaged = skin(rest_of_p.real, rest_of_p.imag).astype(np.float32)
    at_rest = skin(p.real, p.imag).astype(np.float32)
    restored = cv2.remap(imaged, *undrag_maps((h, w), centre, px_per_mm, drag, WIDTH_MM), cv2.INTER_LINEAR)
    inner = np.s_[20:-20, 20:-20]  # away from the border the maps reach past
    assert np.max(np.abs(restored[inner] - at_rest[inner])) < 0.01
    assert np.max(np.abs(imaged[inner] - at_rest[inner])) > 0.2


def test_undrag_maps_are_each_pixel_shifted_by_the_drag_times_the_profile() -> None:
    """The separable maps are the pixel grid plus D phi(|q|) px_per_mm, as undrag defines it, within float32's
    resolution at 640 pixels (6e-5 px; remap resolves 1/32 px)."""
    h, w, px_per_mm, centre = 480, 640, 8.0, (320.3, 239.8)
    drag = -0.7 + 1.1j
    map_x, map_y = undrag_maps((h, w), centre, px_per_mm, drag, WIDTH_MM)
    gy, gx = np.mgrid[0:h, 0:w].astype(np.float64)
    q = (gx - centre[0]) / px_per_mm + 1j * (gy - centre[1]) / px_per_mm
    source = (q - undrag(q, drag, WIDTH_MM)) * px_per_mm  # D phi(|q|) in pixels
    assert map_x.dtype == map_y.dtype == np.float32
    assert np.max(np.abs(map_x - (gx + source.real))) < 1e-4
    assert np.max(np.abs(map_y - (gy + source.imag))) < 1e-4
    assert np.max(np.abs(source)) > 0.9 * abs(drag) * px_per_mm  # the centre moves by the whole drag


def test_frames_without_evidence_take_their_neighbours_drag() -> None:
    # a tracked frame (no feature edge of its own) between two fitted keyframes takes the drag interpolated
    # between theirs; one with a fitted frame on one side only within reach takes that one's; beyond reach none
    fit = DragFit(10.0, {0: 1 + 0j, 4: 3 + 2j, 30: -1j}, 0.1 + 0j, 10.0, 5.0, 30, 300, True)
    filled = fit.filled(range(0, 40), reach=8)
    assert filled.of(2) == pytest.approx(2 + 1j, abs=1e-12)  # half way between frames 0 and 4
    assert filled.of(1) == pytest.approx(1.5 + 0.5j, abs=1e-12)
    assert filled.of(10) == pytest.approx(3 + 2j, abs=1e-12)  # frame 30 is 20 away: frame 4's alone
    assert filled.of(24) == pytest.approx(-1j, abs=1e-12)  # frame 4 is 20 away: frame 30's alone
    assert filled.of(17) == 0j and 17 not in filled.drag_mm  # nothing within reach: no drag
    assert filled.of(4) == 3 + 2j and fit.of(2) == 0j  # fitted drags kept; the fit itself unchanged


def test_the_drag_fitted_on_pairs_reselected_about_the_undragged_skin_is_the_skins() -> None:
    evidence, loads, directions, truth = dragged_serpentine(0.1, seed=3)
    true = np.array(list(truth["drags"].values()))
    near = []  # each match's pairs within three gates of 0.1 mm (MethodOptions.drag_reselect's near pairs)
    for ev in evidence:
        measured = gated(ev, 0.1, 3.0)
        if measured is not None:
            near.append(DragEvidence(ev.i, ev.j, measured[2], measured[0].a))
    gains = []
    for rounds in (0, RESELECT_ROUNDS):  # within one gate of the similarity as measured; then of the undragged skin
        fit = fit_drag(near, loads, directions, reselect_gate_mm=0.1, reselect_rounds=rounds)
        assert fit is not None and fit.kept
        found = np.array([fit.of(k) for k in truth["drags"]])
        gains.append(np.vdot(true, found).real / np.vdot(true, true).real)
    # one gate about the similarity as measured keeps the pairs the drag moved least: 0.63 of the drags; about the
    # skin undragged by that first fit, 0.89 (1.25 gates: 0.97)
    assert gains[0] < 0.75
    assert 0.82 < gains[1] < 1.1
