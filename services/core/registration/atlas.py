"""The session's maps: the main map (the first contact frame's) and the fragments that have not joined it yet.

A clinician scans in strokes and sets the probe down anywhere. Each contact frame is tracked on the map it is
on (the active map); a landing frame, or a frame its map lost, is searched in every map through the place index
(services.core.registration.place_index) and verified by a RANSAC similarity. A frame found nowhere starts a
fragment: a map of its own, with its own pose graph, on which the next frames chain (consecutive contact frames
overlap by ~90 %). When a frame of one map matches a frame of another, the two join by one similarity (the
younger into the older; fragments into the main map) and every frame of the joined one is placed: this is
ORB-SLAM3's Atlas, for a flat map. Frames of a fragment that never joins are not placed. The baselines (the
paper's mosaic registration, the frame-to-frame chain) keep their one map, as published.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from services.core.registration.features import Features
from services.core.registration.frame_prep import PreparedFrame
from services.core.registration.outcome import (
    REASON_BLUR,
    REASON_FEW_KEYPOINTS,
    STATUS_LOST,
    STATUS_OK,
    FrameResult,
    Match,
)
from services.core.registration.place_index import PlaceIndex
from services.core.registration.pose_graph import Edge
from services.core.registration.registrar import LOOP_GATE_MM, MAX_TRACKED_RUN, Registrar

CANDIDATES = 3  # frames the place index proposes that are verified geometrically
MIN_VOTES = 6  # ... each with at least this many descriptor votes
INDEX_SPACING_WINDOWS = 0.25  # a placed frame is indexed when this many window radii from the last one indexed
RECENT_JOIN_FRAMES = 3  # the newest frames of another map (by seq) are always tried for a join: a run just lost
MAX_RELATIVE_SCALE = 1.35  # a verified match's relative scale must lie within this factor of 1
FRAGMENT_MIN_FEATURES = 2  # x min_inliers: a frame needs this many features to start a fragment
TIE_FRAMES = 16  # a join also matches this many joined frames, spread evenly over them ...
TIE_NEIGHBOURS = 3  # ... each onto this many of the map's frames nearest it: one edge alone leaves the joined
# frames' scale and turn to a single match (on the shared clinical scan's first stroke, 2.7 mm at 100 mm), and
# ties near the join alone leave the fragment's far end to its own chain (two of the clinical scan's rows joined
# as fragments: 0.92 mm against 0.60 with both relocalised; ties spread over the fragment: see docs/method.md)


@dataclass(frozen=True)
class PlacedFrame:
    """A placed frame's matching evidence, read back from its map (registrar.FrameEvidence)."""

    index: int
    features: Features
    stretch: float


@dataclass(frozen=True)
class AtlasResult:
    """One frame's registration result, whether it lies on the main map, and the frames a join placed or moved."""

    result: FrameResult
    on_main: bool
    joined: tuple[int, ...] = ()  # frames that joined the main map with this frame (placed now)
    moved: tuple[int, ...] = ()  # main-map frames that the join's refinement moved


@dataclass
class Atlas:
    """Every map of a session, their frames' owner, the place index over them and the map being tracked."""

    new_map: Callable[[], Registrar]
    window_radius_mm: float
    maps: list[Registrar] = field(default_factory=list)  # maps[0] is the main map (empty before the first frame)
    owner: dict[int, Registrar] = field(default_factory=dict)  # placed frame -> the map it is on
    index: PlaceIndex = field(default_factory=PlaceIndex)
    active: Registrar | None = None
    _last_indexed: dict[int, complex] = field(default_factory=dict)  # id(map) -> centre of its last indexed frame

    def __post_init__(self) -> None:
        self.maps = [self.new_map()]

    @property
    def main(self) -> Registrar:
        """Return the main map: the first contact frame's coordinates (it has no frame before that one)."""
        return self.maps[0]

    def fragments(self) -> list[Registrar]:
        """Return the maps that have not joined the main map (newest last)."""
        return self.maps[1:]

    def add(self, pf: PreparedFrame, landing: bool) -> AtlasResult:
        """Return the result of a contact frame: tracked on the active map, else relocalised, else a new fragment.

        landing: the frame starts a stroke (the probe was just set down), so nothing is predicted from motion.
        """
        if self.active is None:
            return self._start_map(self.main.describe(pf), self.main)
        if self.main.options.registration != "keyframes":  # the baselines (paper, sift-chain) as published: one map
            return AtlasResult(self.main.add(pf), True)
        result: FrameResult | None = None
        if not landing and (tracked := self.active.track(pf)) is not None:  # no features, no loops: its keyframe's
            self.owner[pf.index] = self.active
            return AtlasResult(tracked, self.active is self.main)
        pf = self.active.describe(pf)  # a keyframe, a landing or a frame to relocalise: matched by its features
        if not landing:
            result = self.active.add(pf)
            if result.status != STATUS_OK and result.reason == REASON_BLUR:
                return AtlasResult(result, False)
        placed = self.active if result is not None and result.status == STATUS_OK else None
        if placed is None:
            found = self._relocalise(pf)
            if found is not None:
                target, other, match = found
                result = target.relocate(pf, other, match)
                placed = target if result.status == STATUS_OK else None
        if placed is None:
            if len(pf.features) < FRAGMENT_MIN_FEATURES * self.active.options.min_inliers:
                lost = result or FrameResult(pf.index, STATUS_LOST, None, 0, False, reason=REASON_FEW_KEYPOINTS)
                return AtlasResult(lost, False)
            return self._start_map(pf, self.new_map())  # described above
        assert result is not None
        self.active = placed
        self.owner[pf.index] = placed
        indexed = self._index(pf, placed)
        joined, moved = self._join(pf, lookup=indexed) if len(self.maps) > 1 else ((), ())
        self._share_drag_evidence()
        return AtlasResult(result, self.owner[pf.index] is self.main, joined, moved)

    def _share_drag_evidence(self) -> None:
        """Mark every map's skin dragged once one map's refinement found it so (Registrar.drag_evident): the drag
        is the patient's, not a stroke's, so a fragment begun after a lift looks for the closures it breaks too, and a
        join (merge_maps) leaves the map with it. Run after every placed frame and before a map's first."""
        if any(m.drag_evident for m in self.maps):
            for m in self.maps:
                m.drag_evident = True

    def _start_map(self, pf: PreparedFrame, fresh: Registrar) -> AtlasResult:
        """Return the result of a frame that starts a map of its own: the empty main map, or a new fragment."""
        if fresh not in self.maps:
            self.maps.append(fresh)
        self._share_drag_evidence()  # before its first frame: a fragment starts knowing what the maps found
        result = fresh.add(pf)
        self.active = fresh
        self.owner[pf.index] = fresh
        self._index(pf, fresh)
        return AtlasResult(result, fresh is self.main)

    def _index(self, pf: PreparedFrame, on: Registrar) -> bool:
        """Add a placed frame to the place index when it lies far enough from its map's last indexed frame; return
        True when it was added."""
        centre = on.poses[pf.index].t
        last = self._last_indexed.get(id(on))
        if last is not None and abs(centre - last) < INDEX_SPACING_WINDOWS * self.window_radius_mm:
            return False
        self.index.add(pf.index, pf.features.descriptors)
        self._last_indexed[id(on)] = centre
        return True

    def _verify(self, pf: PreparedFrame, other: int, weak: bool = False) -> Match | None:
        """Return the geometrically verified match of a frame on placed frame `other` (its map's RANSAC), or None.

        weak: when the features alone fail the inlier rule, a weaker feature match or a direct alignment of the
        vein maps that reaches the acceptance correlation is taken (the registrar's fallback): frames far apart
        or under other loads share fewer keypoints (on the shared clinical scan, 11 inliers at 24 mm).
        """
        on = self.owner[other]
        match = on._pairwise(pf, other)
        if match is None and weak and on.options.direct_fallback:
            match = on._fallback(pf, other, on.poses[other])
        if match is None or not 1 / MAX_RELATIVE_SCALE <= abs(match.relative.a) <= MAX_RELATIVE_SCALE:
            return None
        if abs(match.relative.t) >= 2 * self.window_radius_mm:  # the windows cannot overlap
            return None
        return match

    def _relocalise(self, pf: PreparedFrame, exclude: Registrar | None = None) -> tuple[Registrar, int, Match] | None:
        """Return (map, placed frame, match) of the best verified place-index candidate (not on `exclude`), or None.

        Without `exclude` (a landing, or a frame its map lost) the weaker verification is allowed too (_verify).
        """
        allowed = None if exclude is None else {f for f in self.index.frames if self.owner.get(f) is not exclude}
        best: tuple[Registrar, int, Match] | None = None
        for other, votes in self.index.query(pf.features.descriptors, CANDIDATES, allowed):
            if votes < MIN_VOTES:
                break
            match = self._verify(pf, other, weak=exclude is None)
            if match is not None and (best is None or match.inliers > best[2].inliers):
                best = (self.owner[other], other, match)
        return best

    def _join(self, pf: PreparedFrame, lookup: bool) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Join another map to the placed frame's map when the frame matches one of its frames.

        lookup: search the place index too (the frames it indexes, a quarter window apart: the frames between see
        what their indexed neighbours see); the other maps' newest frames are tried every frame.
        Returns (frames that joined the main map now, main-map frames the join's refinement moved).
        """
        on = self.owner[pf.index]
        found = self._relocalise(pf, exclude=on) if lookup else None
        if found is None:
            for other_map in self.maps:
                if other_map is on:
                    continue
                for other in [
                    i for i in other_map.order[-RECENT_JOIN_FRAMES - MAX_TRACKED_RUN :] if i in other_map.features
                ][-RECENT_JOIN_FRAMES:]:
                    if other >= pf.index - RECENT_JOIN_FRAMES - 1 and (match := self._verify(pf, other)):
                        found = (other_map, other, match)
                        break
                if found is not None:
                    break
        if found is None:
            return (), ()
        other_map, other, match = found
        was_main = on is self.main or other_map is self.main
        target, source = (on, other_map) if self.maps.index(on) < self.maps.index(other_map) else (other_map, on)
        moved = merge_maps(target, source, pf, other, match, on is target)
        self.maps.remove(source)
        for i in source.order:
            self.owner[i] = target
        if self.active is source:
            self.active = target
        if not was_main:
            return (), ()
        newly = tuple(source.order) if target is self.main else ()
        return newly, tuple(i for i in moved if i not in set(newly))


def merge_maps(
    target: Registrar, source: Registrar, pf: PreparedFrame, other: int, match: Match, pf_on_target: bool
) -> tuple[int, ...]:
    """Move every frame of `source` onto `target` by one similarity and tie them with the join edge; refine.

    The join: frame pf matches placed frame `other` (match: pf mm -> other mm); one of the two is on target, the
    other on source. Returns the frames the refinement moved (> refinement.MOVED_MM).
    """
    if pf_on_target:  # other's pose in target coordinates = P_t(pf) R^-1
        in_target = target.poses[pf.index].compose(match.relative.inverse())
        to_target = in_target.compose(source.poses[other].inverse())
    else:  # pf's pose in target coordinates = P_t(other) R
        in_target = target.poses[other].compose(match.relative)
        to_target = in_target.compose(source.poses[pf.index].inverse())
    for i in source.order:
        target.poses[i] = to_target.compose(source.poses[i])
    target.features.update(source.features)
    target.times.update(source.times)
    target.stretches.update(source.stretches)
    target.veins.update(source.veins)
    target.corrections.forces.update(source.corrections.forces)
    target.corrections.loads.update(source.corrections.loads)
    target.corrections.imu_tilts.update(source.corrections.imu_tilts)
    target.sharpness.extend(source.sharpness)
    target.edges.extend(source.edges)
    target.order = [target.order[0], *sorted(set(target.order[1:]) | set(source.order))]  # the origin stays first
    target.run_start = max(target.run_start, source.run_start)
    target.edges.append(target._edge(pf, other, match))
    target.edges.extend(_ties(target, set(source.order)))
    target.last_global_refine = 0  # the next refinement is global: the joined frames are held by one edge
    if not target.options.refine:
        return ()
    return target.refine()


def _ties(target: Registrar, joined: set[int]) -> list[Edge]:
    """Return edges between joined frames (TIE_FRAMES spread over them) and the map's frames nearest each (after a
    merge).

    Each match must agree with the merged poses within the registrar's LOOP_GATE_MM (a false match lands far).
    """
    ordered = sorted(i for i in joined if i in target.features)  # keyframes, as taken: spread along the fragment
    step = max(1, -(-len(ordered) // TIE_FRAMES))
    newcomers = ordered[::step]
    old = [i for i in target.order if i not in joined and i in target.features]
    edges = []
    for i in newcomers:
        near = sorted(old, key=lambda j: abs(target.poses[j].t - target.poses[i].t))[:TIE_NEIGHBOURS]
        view = PlacedFrame(i, target.features[i], target.stretches[i])
        for j in near:
            if abs(target.poses[j].t - target.poses[i].t) >= 1.6 * target.window_radius_mm:
                continue
            match = target._pairwise(view, j)
            if match is None or abs(target.poses[j].compose(match.relative).t - target.poses[i].t) > LOOP_GATE_MM:
                continue
            edges.append(target._edge(view, j, match))
    return edges
