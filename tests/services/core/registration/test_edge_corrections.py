"""Edge corrections: nothing is corrected before a fit, a kept drag undrags each edge once per fit, the direction of
travel in each frame's own axes, the drag detected while the scan goes on."""

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
from tests.services.core.physics.dragged_serpentine import dragged_serpentine

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


def _gated_edges(
    evidence: list[DragEvidence], poses: dict[int, Similarity], gate_mm: float, drag_pairs: bool
) -> list[Edge]:
    """Return the serpentine's matches as edges whose inliers are the pairs within gate_mm of their least-squares
    similarity (a RANSAC gate) and, if drag_pairs, whose drag pairs are those within two gates."""
    edges = []
    for ev in evidence:
        pj, pi = ev.pairs[:, 0] + 1j * ev.pairs[:, 1], ev.pairs[:, 2] + 1j * ev.pairs[:, 3]
        d = pj - pj.mean()
        a = np.vdot(d, pi - pi.mean()) / np.vdot(d, d).real
        off = np.abs(a * d + pi.mean() - pi)
        inliers = off < gate_mm
        if inliers.sum() >= 8:
            relative = poses[ev.i].inverse().compose(poses[ev.j])
            near = ev.pairs[off < 2 * gate_mm] if drag_pairs else None
            edges.append(
                Edge(ev.i, ev.j, relative, 0.05, inliers=int(inliers.sum()), pairs=ev.pairs[inliers], drag_pairs=near)
            )
    return edges


def test_a_gate_shrinks_the_drag_its_inliers_show_and_the_drag_pairs_restore_it() -> None:
    evidence, loads, _, truth = dragged_serpentine(0.1, seed=3)  # drags of 0.24-1.6 mm, flipping between rows
    poses, true = truth["poses"], np.array(list(truth["drags"].values()))
    gains = []
    for drag_pairs in (False, True):
        corrections = EdgeCorrections(loads=loads)
        fit = corrections.fit_drag(_gated_edges(evidence, poses, 0.1, drag_pairs), sorted(poses), poses)
        assert fit is not None and fit.kept
        found = np.array([fit.of(k) for k in truth["drags"]])
        gains.append(np.vdot(true, found).real / np.vdot(true, true).real)  # the fitted drags against the true
    # a 0.1 mm gate keeps the pairs the drags moved least: the fit finds 0.62 of the drags (the simulated dragged
    # raster's fit, at 2 px, 0.69), the pairs within two gates 0.92
    assert gains[0] < 0.75
    assert 0.85 < gains[1] < 1.1
