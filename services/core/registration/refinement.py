"""When a map's placed poses are re-optimised on its pose graph, and which poses a pass frees, holds and starts from.

A refinement is global (every pose) while the scan is short, at the end, and whenever the placed frames grew by
GLOBAL_GROWTH since the last global pass; in between it is local, around the newest frame. So a minutes-long
examination costs a bounded amount per loop closure, plus global passes whose total is a constant multiple of the
last one (issue 15). The scale pass holds every frame's scale to the tissue law's.
"""

from __future__ import annotations

import numpy as np

from services.core.registration.pose_graph import Edge
from services.core.similarity import Similarity

LOCAL_REFINE_FROM = 400  # placed frames: below this every refinement is global
GLOBAL_GROWTH = 1.25  # ... from it, a global pass when the placed frames grew by this factor since the last one
LOCAL_RADIUS_WINDOWS = 3.0  # a local pass frees the frames within this many window radii of the newest frame
LOCAL_RECENT = 60  # ... and the newest frames
LOCAL_MAX = 240  # ... at most this many of the nearest (an examination's passes pile frames on the same area)
# A global pass refits the view model only when the affine evidence grew by this factor since the last fit (and
# always at the end): fitting it at every global pass of a short scan cost 15 % of a live registering worker's
# time on a 336-frame raster; geometric refits cost a constant multiple of the last one
VIEW_REFIT_GROWTH = 1.25
MOVED_MM = 0.05  # a refined pose that moves a frame by less than this (0.4 px) does not re-render its tiles


def is_global(placed: int, last_global: int, final: bool) -> bool:
    """Return whether a refinement of `placed` frames re-optimises every pose (last_global: at the last such pass)."""
    return final or placed < LOCAL_REFINE_FROM or placed >= GLOBAL_GROWTH * last_global


def local_pass(
    order: list[int], poses: dict[int, Similarity], edges: list[Edge], window_radius_mm: float
) -> tuple[dict[int, Similarity], list[Edge], set[int]]:
    """Return the poses, edges and held frames of a pass re-optimising the poses near the newest frame.

    Near: the LOCAL_MAX nearest within LOCAL_RADIUS_WINDOWS window radii, and the newest LOCAL_RECENT frames;
    the frames they share edges with are held where they are. Its cost is bounded however long the scan
    (issue 15).
    """
    newest = poses[order[-1]].t
    reach = LOCAL_RADIUS_WINDOWS * window_radius_mm
    placed = np.array(order)
    dist = np.abs(np.array([poses[i].t for i in order]) - newest)
    near = np.flatnonzero(dist < reach)
    nearest = near[np.argsort(dist[near], kind="stable")[:LOCAL_MAX]]
    active = {int(i) for i in placed[nearest]} | set(order[-LOCAL_RECENT:])
    active.discard(order[0])
    edges = [e for e in edges if e.i in active or e.j in active]
    held = {e.i for e in edges if e.i not in active} | {e.j for e in edges if e.j not in active}
    if not held:
        held = {order[0]}
    return {i: poses[i] for i in active | held}, edges, held


def scale_pass(
    order: list[int], poses: dict[int, Similarity], targets: dict[int, float], sigma: float
) -> tuple[dict[int, Similarity], dict[int, tuple[float, float]]]:
    """Return the start poses and scale priors of a pass holding each frame's scale |a| to its target.

    Each target is held with relative sigma `sigma`.

    Edges measure scale only relative to a neighbour, so along a chain with few loop closures (a hard scan's
    rows) the scale wanders like a random walk; the tissue law fitted to the loads says what each frame's scale
    is (SessionReconstruction._expected_scales), and holding every frame to it keeps the path's shape and the
    gauge taken from the scales in step.

    Frame 0, the path's origin, is set to its own target and held there (position and yaw unchanged). Held at
    scale 1 while the others followed the law, its edges carried the gap between 1 and its law's scale into
    every other frame's position (a simulated hard scan starting at 30 N: 0.18 mm from frame 1 on). Left free
    with a prior like the others, its weakly tied yaw moved too and turned the whole path (0.26 deg on
    simulated hard s1). docs/accuracy.md, "Frame 0 held to the law's scale".
    """
    first = order[0]
    start = dict(poses)
    if first in targets:  # the whole placement rescaled about frame 0 (at the origin), so the graph's weak
        ratio = targets[first] / abs(poses[first].a)  # pulls toward the start agree with frame 0's scale
        start = {i: Similarity(p.a * ratio, p.t * ratio) for i, p in poses.items()}
    return start, {i: (t, sigma * t) for i, t in targets.items() if i != first}


def moved_frames(refined: dict[int, Similarity], poses: dict[int, Similarity]) -> tuple[int, ...]:
    """Return the frames whose refined pose moves them by more than MOVED_MM from their pose."""
    return tuple(i for i, p in refined.items() if abs(p.t - poses[i].t) > MOVED_MM)
