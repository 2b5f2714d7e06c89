"""Pose graph: loop closure removes drift, a gross false loop edge is down-weighted, place_node averages, scale
priors hold a drifting chain, a mean-scale prior keeps disagreeing edges from shrinking the map; its normal
equations solved as spsolve solves them."""

from __future__ import annotations

import cmath

import numpy as np
import pytest

from services.core.registration.pose_graph import Edge, optimise_poses, place_node
from services.core.similarity import IDENTITY, Similarity
from tests.tolerances import TOL

N = 30
EDGE_SIGMA_MM = 0.05


def _circle_truth() -> dict[int, Similarity]:
    """True poses of a 30-frame probe loop: a 30 mm radius circle back to the start, yaw wobbling +-0.3 rad."""
    ang = np.linspace(0, 2 * np.pi, N, endpoint=False)
    poses = {
        k: Similarity(cmath.exp(1j * 0.3 * np.sin(ang[k])), complex(30 * np.cos(ang[k]) - 30, 30 * np.sin(ang[k])))
        for k in range(N)
    }
    poses[0] = IDENTITY
    return poses


def _relative(truth: dict[int, Similarity], i: int, j: int) -> Similarity:
    return truth[i].inverse().compose(truth[j])


@pytest.fixture(scope="module")
def chain() -> tuple[dict[int, Similarity], dict[int, Similarity], list[Edge], Edge]:
    """(truth, dead-reckoned initial poses, noisy chain edges, exact loop-closure edge 0 -> 29), seeded."""
    rng = np.random.default_rng(0)
    truth = _circle_truth()
    edges = []
    for k in range(N - 1):
        rel = _relative(truth, k, k + 1)
        noisy = Similarity(
            rel.a * cmath.exp(1j * rng.normal(0, 0.003)), rel.t + complex(*rng.normal(0, EDGE_SIGMA_MM, 2))
        )
        edges.append(Edge(k, k + 1, noisy, EDGE_SIGMA_MM))
    initial = {0: IDENTITY}
    for e in edges:
        initial[e.j] = initial[e.i].compose(e.relative)
    loop = Edge(0, N - 1, _relative(truth, 0, N - 1), EDGE_SIGMA_MM, loop=True)
    return truth, initial, edges, loop


def _max_shift_mm(a: dict[int, Similarity], b: dict[int, Similarity]) -> float:
    return max(abs(a[k].t - b[k].t) for k in a)


def test_loop_closure_reduces_final_error(chain) -> None:
    truth, initial, edges, loop = chain
    before = abs(initial[N - 1].t - truth[N - 1].t)
    assert before > 0.3  # the dead-reckoned chain has drifted (measured 0.63 mm)
    solution = optimise_poses(initial, [*edges, loop], fixed=0)
    after = abs(solution.poses[N - 1].t - truth[N - 1].t)
    assert after * 5 < before  # measured 0.0096 mm: a 65x reduction
    assert solution.poses[0] == IDENTITY  # the fixed node is held
    assert np.all(solution.edge_weights > 0.9)  # all edges consistent: none down-weighted


def test_gross_false_loop_edge_is_down_weighted(chain) -> None:
    truth, initial, edges, loop = chain
    clean = optimise_poses(initial, [*edges, loop], fixed=0)
    rel = _relative(truth, 5, 20)
    bad = Edge(5, 20, Similarity(rel.a, rel.t + 30.0), EDGE_SIGMA_MM, loop=True)  # 30 mm wrong
    robust = optimise_poses(initial, [*edges, loop, bad], fixed=0)
    plain = optimise_poses(initial, [*edges, loop, bad], fixed=0, robust_mm=1e6)  # ~no robust weighting
    assert robust.edge_weights[-1] < 1e-3  # measured 3.4e-4
    assert np.all(robust.edge_weights[:-1] > 0.9)
    # Without robustness the bad edge drags the loop by ~22 mm. The Cauchy weight leaves a bounded pull
    # (~ c^2 / r ~ 0.01 mm per edge, c = sigma + 0.5 mm) shared by the 15 edges between nodes 5 and 20:
    # measured 0.16 mm, well under the solution's own error against the truth (max 0.52 mm here).
    assert _max_shift_mm(plain.poses, clean.poses) > 10.0
    assert _max_shift_mm(robust.poses, clean.poses) < 0.25
    assert abs(robust.poses[N - 1].t - truth[N - 1].t) < 0.1


def test_consistent_chain_is_left_in_place(chain) -> None:
    _truth, initial, edges, _loop = chain
    solution = optimise_poses(initial, edges, fixed=0)  # a tree: every edge can be met exactly
    # lsqr to atol 1e-12 on O(30 mm) values: any shift above 1e-6 mm would be a real change
    assert _max_shift_mm(solution.poses, initial) < 1e-6
    assert np.all(solution.residuals_mm < 1e-6)


def test_place_node_weights_edges_by_inverse_variance() -> None:
    placed = {0: IDENTITY, 1: Similarity(1 + 0j, 10 + 0j)}
    # edge 0 -> 2 (sigma 1): estimate a = 1, t = 4
    e1 = Edge(0, 2, Similarity(1 + 0j, 4 + 0j), sigma_mm=1.0)
    # edge 2 -> 1 (sigma 0.5, stored the other way round): T_2 = T_1 rel^-1, rel^-1 = (2, -8),
    # so the estimate is a = 2, t = 10 - 8 = 2
    e2 = Edge(2, 1, Similarity(0.5 + 0j, 4 + 0j), sigma_mm=0.5)
    # weights 1/sigma^2 = 1 and 4: a = (1 * 1 + 4 * 2) / 5 = 1.8, t = (1 * 4 + 4 * 2) / 5 = 2.4
    pose = place_node(placed, [e1, e2, Edge(3, 4, IDENTITY, 0.1)], node=2)  # the 3 -> 4 edge is ignored
    assert pose.a == pytest.approx(1.8 + 0j, abs=TOL.float64_abs)
    assert pose.t == pytest.approx(2.4 + 0j, abs=TOL.float64_abs)


def test_place_node_without_placed_neighbour_raises() -> None:
    with pytest.raises(ValueError, match="no edge"):
        place_node({0: IDENTITY}, [Edge(3, 4, IDENTITY, 0.1)], node=4)


def test_a_part_cut_off_by_a_dropped_edge_keeps_its_poses() -> None:
    # the fixed node's only edge is grossly wrong (dropped as an outlier), so the rest of the chain loses its
    # link to it. Without a prior the chain's gauge is free and IRLS let it shrink towards scale 0 (seen on a
    # simulated hard scan: scales of 1e-15); with the weak prior it stays where registration put it.
    step = Similarity(1 + 0j, 10 + 0j)
    initial = {k: Similarity(1 + 0j, complex(10 * k, 0)) for k in range(8)}
    edges = [Edge(0, 1, Similarity(cmath.exp(0.5j) * 1.3, 40 + 25j), 0.05)]  # 30 mm and 30 % wrong
    edges += [Edge(k, k + 1, step, 0.05) for k in range(1, 7)]
    edges += [Edge(k, k + 2, Similarity(1 + 0j, 20.3 + 0j), 0.05) for k in range(1, 6)]  # 1.5 % tension
    solution = optimise_poses(initial, edges, fixed=0)
    assert solution.edge_weights[0] == 0.0  # the wrong edge is dropped ...
    # ... and the chain keeps its scale and place: the tension's least-squares compromise moves them by up to
    # 1.5 % (measured 0.985) and 0.2 mm; without the prior they collapsed to scale 1e-14
    for k in range(8):
        assert abs(abs(solution.poses[k].a) - 1) < 0.03
        assert abs(solution.poses[k].t - initial[k].t) < 1.0


def test_held_nodes_stay_put_and_anchor_the_free_ones() -> None:
    """A local refinement: nodes 0 and 4 held, 1-3 free between them; the free ones settle on the exact chain
    (tolerance 1e-5 mm: noise-free edges; the weak pose priors, 50 mm, pull by ~(0.05/50)^2 of the 1 mm start
    offset) while the held ones do not move at all."""
    truth = {i: Similarity(1 + 0j, complex(3.0 * i, 0.5 * i)) for i in range(5)}
    start = {i: (p if i in (0, 4) else Similarity(p.a, p.t + complex(0.8, -0.6))) for i, p in truth.items()}
    edges = [Edge(i, i + 1, truth[i].inverse().compose(truth[i + 1]), 0.05) for i in range(4)]
    solution = optimise_poses(start, edges, fixed={0, 4})
    assert solution.poses[0] == start[0] and solution.poses[4] == start[4]
    for i in (1, 2, 3):
        assert abs(solution.poses[i].t - truth[i].t) < 1e-5


def test_an_edge_is_measured_where_its_inliers_are() -> None:
    # two feature edges between the same frames: A's inliers lie off-centre and close together (centre 30 mm,
    # spread 5 mm) and its rotation is off by 1 deg, with its translation right where its inliers are, as a
    # least-squares fit over such inliers gives; B's are spread wide about -10 mm and exact. Measured at their
    # inliers, B's rotation outweighs A's (20 / 5)^2 = 16 times and the frame lands within 0.03 mm and 0.1 deg of
    # the truth. Measured at the frame's centre with one lever (lever_mm 0), A carried its rotation error 30 mm
    # out into its translation and half of it into the pose: 0.26 mm and 0.5 deg off.
    truth = Similarity(cmath.exp(1j * 0.2), complex(12.0, -3.0))
    centre_a = complex(30.0, 0.0)
    turned = truth.a * cmath.exp(1j * np.radians(1.0))
    tilted = Similarity(turned, truth.a * centre_a + truth.t - turned * centre_a)  # = truth at centre_a
    initial = {0: IDENTITY, 1: truth}

    def solve(lever_a: float, centre_a_mm: complex, lever_b: float, centre_b_mm: complex) -> Similarity:
        a = Edge(0, 1, tilted, EDGE_SIGMA_MM, inliers=40, centre=centre_a_mm, lever_mm=lever_a)
        b = Edge(0, 1, truth, EDGE_SIGMA_MM, inliers=40, centre=centre_b_mm, lever_mm=lever_b)
        return optimise_poses(initial, [a, b], fixed=0).poses[1]

    where_inliers_are = solve(5.0, centre_a, 20.0, complex(-10.0, 0.0))
    assert abs(where_inliers_are.t - truth.t) < 0.03
    assert abs(np.degrees(np.angle(where_inliers_are.a / truth.a))) < 0.1
    at_the_centre = solve(0.0, 0j, 0.0, 0j)  # the graph's default lever, both measured at frame 1's centre
    assert abs(at_the_centre.t - truth.t) > 0.2


def test_scale_priors_hold_a_drifting_chain_to_its_targets_and_leave_its_turns() -> None:
    # a chain whose every edge says the next frame is 0.3 % larger (a registration's scale bias): without a prior
    # its last frame ends 9 % large (1.003^29); held to 1 with 0.5 % per frame, every scale stays within 1 %
    truth = _circle_truth()
    edges = []
    for k in range(N - 1):
        rel = _relative(truth, k, k + 1)
        edges.append(Edge(k, k + 1, Similarity(rel.a * 1.003, rel.t), EDGE_SIGMA_MM))
    initial = {0: IDENTITY}
    for e in edges:
        initial[e.j] = initial[e.i].compose(e.relative)
    free = optimise_poses(initial, edges, fixed=0)
    held = optimise_poses(initial, edges, fixed=0, scale_priors={k: (1.0, 0.005) for k in range(1, N)})
    assert abs(free.poses[N - 1].a) == pytest.approx(1.003 ** (N - 1), rel=1e-6)
    assert max(abs(abs(p.a) - 1.0) for p in held.poses.values()) < 0.01  # measured 0.0055
    for k in range(N):  # the prior acts on scale only (linearised about each start: turns move by 1.4e-5 rad at most)
        assert cmath.phase(held.poses[k].a) == pytest.approx(cmath.phase(free.poses[k].a), abs=1e-4)


def test_a_mean_scale_prior_keeps_disagreeing_edges_from_shrinking_the_map() -> None:
    # the residuals t_j - t_i - a_i t_ij shrink with every free frame's scale at once: edges among the free frames
    # that disagree by 1.5 mm (a dragged skin not undone yet) pull the whole map but the held frame 0 toward scale
    # 0 (measured 0.36 in one solve, ~0.0001 after six), which frame 0's one edge cannot stop; its mean held at 1
    # with 0.1 %, it stays (measured 0.995, every frame within 1.1 % of 1) and the frames near the truth
    truth = _circle_truth()
    rng = np.random.default_rng(0)
    edges = [Edge(k, k + 1, _relative(truth, k, k + 1), EDGE_SIGMA_MM) for k in range(N - 1)]
    for k in range(1, N - 3):
        for d in (2, 3):
            rel = _relative(truth, k, k + d)
            edges.append(Edge(k, k + d, Similarity(rel.a, rel.t + complex(*rng.normal(0, 1.5, 2))), EDGE_SIGMA_MM))
    free = optimise_poses(truth, edges, fixed=0)
    held = optimise_poses(truth, edges, fixed=0, mean_scale=(1.0, 1e-3))
    assert np.mean([abs(free.poses[k].a) for k in range(1, N)]) < 0.5
    assert np.mean([abs(held.poses[k].a) for k in range(1, N)]) == pytest.approx(1.0, abs=0.01)
    assert max(abs(abs(held.poses[k].a) - 1.0) for k in range(1, N)) < 0.03
    assert _max_shift_mm(held.poses, truth) < 5.0  # measured 3.0 mm; collapsed, 20 mm
    assert _max_shift_mm(free.poses, truth) > 10.0
