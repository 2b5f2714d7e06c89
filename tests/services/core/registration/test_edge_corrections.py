"""Edge corrections: nothing is corrected before a fit, a kept drag undrags each edge once per fit, the direction of
travel in each frame's own axes, the drag detected while the scan goes on, and its pairs chosen about the undragged
skin (drag_reselect)."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.physics.drag import DragEvidence, DragFit
from services.core.registration.edge_corrections import (
    DIRECTION_GAP,
    EdgeCorrections,
    directions_of_travel,
    view_evidence,
)
from services.core.registration.pose_graph import Edge
from services.core.similarity import IDENTITY, Similarity
from tests.services.core.physics.dragged_serpentine import WIDTH_MM, dragged_serpentine, gated

# matched points of frame j and frame i (mm): a spread of pairs, frame j 2 mm along x of frame i
PAIRS = np.array([[x, y, x + 2.0, y] for x in (-8.0, 0.0, 8.0) for y in (-6.0, 0.0, 6.0)])


def _drag(kept: bool) -> DragFit:
    return DragFit(12.0, {0: 0.3 + 0j, 1: -0.2 + 0.1j}, 0.02 + 0j, 10.0, 2.0, 1, len(PAIRS), kept)


def test_before_any_fit_edges_and_views_are_as_measured() -> None:
    corrections = EdgeCorrections()
    edges = [Edge(0, 1, Similarity(1 + 0j, 2 + 0j), 0.05, pairs=PAIRS)]
    assert corrections.undeformed(edges, {0: IDENTITY, 1: IDENTITY}) is edges
    assert corrections.undragged(edges[0]) is edges[0]
    assert np.array_equal(corrections.view(0, {0: IDENTITY}), np.eye(2))
    assert not corrections.dragged()


def test_a_kept_drag_undrags_each_edge_once_per_fit() -> None:
    corrections = EdgeCorrections(drag_fit=_drag(kept=True))
    edge = Edge(0, 1, Similarity(1 + 0j, 2 + 0j), 0.05, pairs=PAIRS)
    undragged = corrections.undragged(edge)
    assert undragged.relative != edge.relative
    assert corrections.undragged(edge) is undragged  # cached by the edge's identity
    assert corrections.undeformed([edge], {0: IDENTITY, 1: IDENTITY}) == [undragged]
    assert EdgeCorrections(drag_fit=_drag(kept=False)).undragged(edge) is edge  # a drag not kept is no drag
    assert corrections.undragged(Edge(0, 1, edge.relative, 0.05)) == Edge(0, 1, edge.relative, 0.05)  # no pairs


def test_directions_of_travel_are_in_each_frames_own_axes() -> None:
    turned = 1j  # frames turned 90 deg: travel along the map's +x is along their -y
    order = [0, 1, 2, 3 + DIRECTION_GAP + 1]
    poses = {i: Similarity(turned, complex(float(i), 0.0)) for i in order[:3]}
    poses[order[3]] = Similarity(turned, 40 + 0j)
    directions = directions_of_travel(order, poses)
    assert all(abs(directions[i] - (-1j)) < 1e-12 for i in order[:3])
    assert directions[order[3]] == 0j  # alone across a gap: no direction


def test_view_evidence_counts_the_edges_with_an_affine_on_their_inliers() -> None:
    affine = np.hstack([np.eye(2), np.zeros((2, 1))])
    edges = [Edge(0, 1, IDENTITY, 0.05, view_affine=affine), Edge(1, 2, IDENTITY, 0.05)]
    assert view_evidence(edges) == 1


@pytest.mark.parametrize(("gain_mm_per_n", "evident"), [(0.1, True), (0.0, False)])
def test_the_drag_is_detected_while_the_scan_goes_on_without_being_kept(gain_mm_per_n: float, evident: bool) -> None:
    evidence, loads, _, truth = dragged_serpentine(gain_mm_per_n, seed=3)  # a serpentine of 3 rows, dragged or not
    poses = truth["poses"]
    edges = [
        Edge(ev.i, ev.j, poses[ev.i].inverse().compose(poses[ev.j]), 0.05, inliers=len(ev.pairs), pairs=ev.pairs)
        for ev in evidence
    ]
    corrections = EdgeCorrections(loads=loads)
    assert corrections.drag_evident(edges, sorted(poses), poses) is evident
    assert corrections.drag_fit is None  # detected only: the drag is undone at the end (fit_drag)


def _gated_edges(evidence: list[DragEvidence], gate_mm: float, near_gates: float) -> list[Edge]:
    """Return the serpentine's matches as edges measured behind a RANSAC gate of gate_mm (dragged_serpentine.gated),
    their drag pairs those within near_gates gates (None at 0)."""
    edges = []
    for ev in evidence:
        measured = gated(ev, gate_mm, near_gates)
        if measured is not None:
            relative, inliers, near = measured
            drag_pairs = near if near_gates > 0 else None
            edges.append(Edge(ev.i, ev.j, relative, 0.05, inliers=len(inliers), pairs=inliers, drag_pairs=drag_pairs))
    return edges


def test_a_gate_shrinks_the_drag_its_inliers_show_and_the_drag_pairs_restore_it() -> None:
    evidence, loads, _, truth = dragged_serpentine(0.1, seed=3)  # drags of 0.24-1.6 mm, flipping between rows
    poses, true = truth["poses"], np.array(list(truth["drags"].values()))
    gains = []
    for near_gates in (0.0, 2.0):  # the inliers; the pairs within two gates
        corrections = EdgeCorrections(loads=loads)
        fit = corrections.fit_drag(_gated_edges(evidence, 0.1, near_gates), sorted(poses), poses)
        assert fit is not None and fit.kept
        found = np.array([fit.of(k) for k in truth["drags"]])
        gains.append(np.vdot(true, found).real / np.vdot(true, true).real)  # the fitted drags against the true
    # a 0.1 mm gate keeps the pairs the drags moved least: the fit finds 0.63 of the drags (the simulated dragged
    # raster's fit, at 2 px, 0.69), the pairs within two gates 0.92
    assert gains[0] < 0.75
    assert 0.85 < gains[1] < 1.1


def test_edges_undragged_over_their_gated_inliers_stay_off_and_reselected_about_the_undragged_skin_do_not() -> None:
    evidence, loads, _, truth = dragged_serpentine(0.1, seed=3)  # drags of 0.24-1.6 mm, flipping between rows
    poses = truth["poses"]
    edges = _gated_edges(evidence, 0.1, 3.0)
    grid = np.array([x + 1j * y for x in (-10.0, 0.0, 10.0) for y in (-8.0, 0.0, 8.0)])  # over a window (mm)
    errors = []
    for gate_mm in (0.0, 0.1):  # the undragged inliers; the near pairs within one gate of the undragged skin
        corrections = EdgeCorrections(loads=loads, gate_mm=gate_mm)
        corrections.drag_fit = DragFit(WIDTH_MM, dict(truth["drags"]), 0j, 1.0, 0.0, len(edges), 0, True)  # exact
        off = []
        for e in edges:
            measured, true = corrections.undragged(e).relative, poses[e.i].inverse().compose(poses[e.j])
            off.append(np.sqrt(np.mean(np.abs(measured.a * grid + measured.t - (true.a * grid + true.t)) ** 2)))
        errors.append(float(np.sqrt(np.mean(np.square(off)))))
    # with the drags undone exactly, the edges measured on the gate's inliers stay 0.030-0.033 mm RMS off over the
    # window (seeds 1-4; the gate kept the pairs the drag moved least, so their noise leans against the drag), those
    # re-measured about the undragged skin 0.015-0.016 (the noise's own floor with ~40 pairs)
    assert errors[0] > 0.025
    assert errors[1] < 0.02
    assert errors[1] < 0.6 * errors[0]


def test_drag_pair_gate_zero_fits_the_inliers_alone_whatever_near_pairs_are_kept() -> None:
    evidence, loads, _, truth = dragged_serpentine(0.1, seed=3)
    poses = truth["poses"]
    edges = _gated_edges(evidence, 0.1, 3.0)
    inliers_only = [Edge(e.i, e.j, e.relative, 0.05, inliers=e.inliers, pairs=e.pairs) for e in edges]
    kept_near = EdgeCorrections(loads=loads, gate_mm=0.1, drag_pair_gates=0.0).fit_drag(edges, sorted(poses), poses)
    alone = EdgeCorrections(loads=loads).fit_drag(inliers_only, sorted(poses), poses)
    assert kept_near is not None and alone is not None
    assert kept_near.drag_mm == alone.drag_mm  # the same evidence, the same fit
