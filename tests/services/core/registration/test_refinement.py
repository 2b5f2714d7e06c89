"""Refinement: global passes while short, at the end and as the map grows, local ones in between; a local pass's
free and held frames; the scale pass rescaling about frame 0; which frames count as moved."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.core.methods import method_options
from services.core.registration.pose_graph import Edge
from services.core.registration.refinement import (
    GLOBAL_GROWTH,
    LOCAL_RADIUS_WINDOWS,
    LOCAL_RECENT,
    LOCAL_REFINE_FROM,
    MOVED_MM,
    is_global,
    local_pass,
    moved_frames,
    scale_pass,
)
from services.core.registration.registrar import Registrar
from services.core.similarity import IDENTITY, Similarity


def test_a_refinement_is_global_while_short_at_the_end_and_when_grown() -> None:
    assert is_global(LOCAL_REFINE_FROM - 1, LOCAL_REFINE_FROM - 1, final=False)
    assert not is_global(LOCAL_REFINE_FROM + 10, LOCAL_REFINE_FROM, final=False)
    assert is_global(LOCAL_REFINE_FROM + 10, LOCAL_REFINE_FROM, final=True)
    assert is_global(round(GLOBAL_GROWTH * 800), 800, final=False)


def test_a_local_pass_frees_the_near_and_newest_frames_and_holds_their_neighbours() -> None:
    # a straight chain 3.6 mm per frame: the newest LOCAL_RECENT frames reach farther back than the window radii
    n, step, radius = 600, 3.6, 20.0
    order = list(range(n))
    poses = {i: Similarity(1 + 0j, complex(step * i, 0.0)) for i in order}
    edges = [Edge(i - 1, i, Similarity(1 + 0j, complex(step, 0.0)), 0.05) for i in order[1:]]
    assert LOCAL_RADIUS_WINDOWS * radius < step * LOCAL_RECENT
    start, used, held = local_pass(order, poses, edges, radius)
    first_free = n - LOCAL_RECENT
    assert held == {first_free - 1}  # the one frame outside sharing an edge with a freed one
    assert set(start) == set(range(first_free - 1, n))
    assert {(e.i, e.j) for e in used} == {(i - 1, i) for i in range(first_free, n)}


def test_the_scale_pass_rescales_the_whole_placement_about_frame_0() -> None:
    poses = {0: IDENTITY, 1: Similarity(1.01 + 0j, 10 + 2j)}
    start, priors = scale_pass([0, 1], poses, {0: 0.97, 1: 0.98}, 0.005)
    ratio = 0.97
    assert start[0] == Similarity(ratio + 0j, 0j)
    assert start[1].a == pytest.approx(1.01 * ratio) and start[1].t == pytest.approx((10 + 2j) * ratio)
    assert priors == {1: (0.98, 0.005 * 0.98)}  # frame 0 is held, not pulled


def test_only_frames_moved_more_than_moved_mm_count_as_moved() -> None:
    poses = {0: IDENTITY, 1: IDENTITY, 2: IDENTITY}
    refined = {0: IDENTITY, 1: Similarity(1 + 0j, complex(0.5 * MOVED_MM, 0)), 2: Similarity(1 + 0j, 2 * MOVED_MM)}
    assert moved_frames(refined, poses) == (2,)


def test_long_scan_refines_locally_between_growing_global_passes() -> None:
    """Issue 15: past LOCAL_REFINE_FROM placed frames a refinement frees only the frames near the newest one
    (far ones do not move at all: tolerance 0) until the placed frames grew by GLOBAL_GROWTH; then it is
    global again, and the final refinement always is."""
    options = dataclasses.replace(method_options("best"), fit_tilt=False)
    registrar = Registrar(options, px_per_mm=8.0, window_radius_mm=20.0, centre_px=(320.0, 240.0))
    n = LOCAL_REFINE_FROM + 50
    rng = np.random.default_rng(5)
    truth = {i: Similarity(1 + 0j, complex(3.6 * i, 0.0)) for i in range(n)}
    for i in range(n):  # placed with a small random error, chained by exact edges
        registrar.poses[i] = Similarity(1 + 0j, truth[i].t + complex(*rng.normal(0.0, 0.3, 2)))
        registrar.order.append(i)
        if i:
            registrar.edges.append(Edge(i - 1, i, truth[i - 1].inverse().compose(truth[i]), 0.05))
    registrar.last_global_refine = n  # a global pass just ran: the next one is local
    before = dict(registrar.poses)
    moved = registrar.refine()
    assert moved and min(moved) >= n - 100, "only frames near the newest one move"
    assert all(registrar.poses[i] == before[i] for i in range(n - 100))
    registrar.last_global_refine = int(n / GLOBAL_GROWTH)  # grown enough: global again
    moved = registrar.refine()
    assert min(moved) < 50, "a global pass moves the early frames too"
    registrar.last_global_refine = n
    registrar.poses = dict(before)
    assert min(registrar.refine(final=True)) < 50  # the final refinement is global


def test_the_scale_prior_sets_frame_0_to_its_own_target_and_keeps_it_the_origin() -> None:
    """Frame 0 is held at the scale the tissue law gives it, not at 1: a chain registered from frame 0 at scale 1
    (its image 3 % larger than the law's unit, as a frame rectified at 30 N with a compliance a few % off) comes out
    at the truth. The edges and targets are exact and the start is rescaled with frame 0, so only the solver's
    rounding is left: tolerance 1e-6 (mm, and of a; 1e-16 measured). Held at 1, frame 0 put frame 1 0.47 mm off
    and frame 7 1.13 mm; rescaling frame 0 alone left the graph's weak pull toward the registered poses (0.021 mm
    at frame 7)."""
    options = dataclasses.replace(method_options("best"), fit_tilt=False)
    registrar = Registrar(options, px_per_mm=8.0, window_radius_mm=20.0, centre_px=(320.0, 240.0))
    turn = np.exp(0.02j)
    truth = {0: Similarity(0.97 + 0j, 0j)} | {k: Similarity(turn**k, complex(15.0 * k, 2.0 * k)) for k in range(1, 8)}
    registered = {0: IDENTITY}
    for k in range(1, 8):
        relative = truth[k - 1].inverse().compose(truth[k])
        registrar.edges.append(Edge(k - 1, k, relative, 0.05))
        registered[k] = registered[k - 1].compose(relative)
    registrar.poses = dict(registered)
    registrar.order = list(range(8))
    registrar.refine_scales({k: abs(p.a) for k, p in truth.items()}, 0.005)
    assert registrar.poses[0].t == 0j and registrar.poses[0].a == pytest.approx(0.97, abs=1e-12)
    for k in range(1, 8):
        assert abs(registrar.poses[k].t - truth[k].t) < 1e-6, k
        assert abs(registrar.poses[k].a - truth[k].a) < 1e-6, k
