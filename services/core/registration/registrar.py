"""Sequential registration of prepared frames against what is already placed (spec §2 "Pose").

Three strategies share one state machine: `previous` (frame-to-frame chaining, the SfM-like baseline),
`mosaic` (the paper: match against the features of the mosaic around the predicted position, keep yaw and
x/y), and `keyframes` (match against several overlapping placed frames, each match an edge of a similarity
pose graph; loop closures trigger a robust global re-optimisation).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.core.methods import MethodOptions
from services.core.physics.drag import along_travel
from services.core.registration.direct_alignment import (
    AlignmentImage,
    DirectFit,
    align,
    alignment_image,
    correlation,
    overlap_pairs,
)
from services.core.registration.drag_match import DraggedMatch, estimate_dragged_match
from services.core.registration.edge_corrections import EdgeCorrections, step_of_travel, view_evidence
from services.core.registration.features import Features
from services.core.registration.frame_prep import PreparedFrame, describe_frame, tracks_frames, tracks_when_behind
from services.core.registration.matching import SimilarityFit, estimate_similarity, match_features
from services.core.registration.outcome import (
    REASON_BLUR,
    REASON_FEW_INLIERS,
    REASON_FEW_KEYPOINTS,
    REASON_IMPLAUSIBLE,
    REASON_LOW_CORRELATION,
    STATUS_LOST,
    STATUS_OK,
    STATUS_REJECTED,
    FrameEvidence,
    FrameResult,
    Match,
    feature_match,
)
from services.core.registration.pose_graph import Edge, optimise_poses, place_node
from services.core.registration.refinement import VIEW_REFIT_GROWTH, is_global, local_pass, moved_frames, scale_pass
from services.core.registration.sparse_alignment import SparseTemplate, sparse_align, sparse_template
from services.core.similarity import IDENTITY, Similarity

# A match to an older frame that places the new frame farther than this from where the match to the latest frame
# places it is a false loop closure. It was max_jump_mm / 5 = 3 mm, which also refused true ones once a hard scan's
# chain had drifted 3 mm between passes: on simulated hard s1 / s2 no loop closed after frame 140, and the last
# rows drifted to 8.5 mm (path 2.32 / 3.79 mm; 1.79 / 3.08 mm at 6 mm, the same from 6 to 15 mm; the shared scans
# and the simulated raster, revisit and short cells unchanged). False matches land tens of mm away, and the pose
# graph's robust weights take the rest.
LOOP_GATE_MM = 6.0
# before a global refinement finds the skin dragged, a closure gated about the drag model is kept only when both
# drags it fitted are at least this long and along their frame's travel (physics.drag.along_travel): a tissue's own
# deformation between rows also fits the model (on a simulated linear-law raster it turned the path: 0.153 ->
# 0.184 mm), a window's drag lies along its stroke
DRAG_MATCH_MIN_MM = 0.2
DRAG_MATCH_WIDTH_MM = 15.0  # the drag profile's width a closure assumes before the scan's own is fitted
MIN_DIRECT_OVERLAP = 0.15  # a direct alignment must overlap this share of the placed frame's window
DIRECT_SIGMA_MM = 0.05  # a direct edge's sigma at perfect correlation (about twice a feature edge's)
DIRECT_SIGMA_PER_DECORRELATION_MM = 1.0  # ... growing by this per unit of (1 - correlation)
ALIGNMENT_CACHE = 12  # placed frames whose alignment pyramids are kept (the latest ones: most often matched)
TRACK_PAIR_STEP_PX = 8  # a tracked edge's overlap sampled every this many alignment pixels (2 mm): its drag undone
FIRST_KEYFRAMES = 10  # a map's first frames are all keyframes: the map's axes are its first frame's (held)
DRAG_CHECK_EDGES = 600  # the newest edges a global refinement checks for a dragged skin (a raster's shows by its
# second row): a long examination's checks cost no more than a short one's
SAME_PLACE_PX = 2.0  # keypoints matched within this of each other (rectified pixels) are one place (A-SIFT's views)
MEAN_SCALE_SIGMA = 1e-3  # a global pass while the scan goes on: the map's mean scale held at its band's edge
NEAR_PAIR_GATES = 3.0  # MethodOptions.drag_reselect: the pairs a match keeps, within this many RANSAC gates
TEMPLATE_CACHE = 16  # placed frames kept as sparse templates: the keyframe tracked on and the closures' last ones
TRACK_CLOSURE_OVERLAP = 0.5  # a tracked frame's closure must overlap this share of the older keyframe's window
MAX_TRACKED_RUN = 8  # frames after a keyframe: the next one is a keyframe however well it tracks (loops, drag)
# placed frames whose centres lie within this many window radii of a frame's (predicted) centre are matched with it;
# each frame lost since the last placed one widens the search by as much again (Registrar._search_radius_mm)
SEARCH_RADIUS_WINDOWS = 1.6


def _vein_scale(pf: PreparedFrame) -> float:
    """Return the vein map's pixels per full-resolution pixel of a prepared frame."""
    return pf.vein.shape[1] / pf.image.shape[1]


@dataclass(eq=False)  # a map is itself (services.core.registration.atlas keeps several): compared by identity
class Registrar:
    """The growing registration state of one session (frames fed in index order)."""

    options: MethodOptions
    px_per_mm: float
    window_radius_mm: float
    centre_px: tuple[float, float]  # the principal point (rectified pixels): direct alignment's centre
    # the probe's forces, the view model and skin drag learned from them and the edges, the edges corrected for both
    corrections: EdgeCorrections = field(default_factory=EdgeCorrections)
    poses: dict[int, Similarity] = field(default_factory=dict)
    features: dict[int, Features] = field(default_factory=dict)
    times: dict[int, float] = field(default_factory=dict)
    stretches: dict[int, float] = field(default_factory=dict)
    edges: list[Edge] = field(default_factory=list)
    sharpness: list[float] = field(default_factory=list)
    order: list[int] = field(default_factory=list)
    loops_since_refine: int = 0
    last_global_refine: int = 0  # placed frames at the last global refinement
    run_start: int = 0  # the first frame of the current run (placed after a landing or a relocalisation)
    drag_evident: bool = False  # a global refinement found the skin dragged (options.loop_ransac_px applies)
    # placed frames: vein map, its window mask bit-packed (np.packbits of mask > 0: 8x smaller), vein scale
    veins: dict[int, tuple[np.ndarray, np.ndarray, float]] = field(default_factory=dict)
    _pyramids: dict[int, AlignmentImage] = field(default_factory=dict)
    _templates: dict[int, SparseTemplate] = field(default_factory=dict)  # keyframes as sparse templates (newest used)

    def predict(self, t_s: float) -> Similarity | None:
        """Return the constant-velocity prediction of the pose at time t_s, or None before any frame."""
        if not self.order:
            return None
        last = self.order[-1]
        p1 = self.poses[last]
        if len(self.order) < 2:
            return p1
        prev = self.order[-2]
        if prev < self.run_start:  # the run began after a jump (a landing, a relocalisation): no velocity yet
            return p1
        p0 = self.poses[prev]
        dt = self.times[last] - self.times[prev]
        if dt <= 0:
            return p1
        k = min((t_s - self.times[last]) / dt, 3.0)
        return Similarity(p1.a * (p1.a / p0.a) ** k, p1.t + (p1.t - p0.t) * k)

    def _is_blurred(self, pf: PreparedFrame) -> bool:
        """Return True when the frame is much less sharp than the recent sharp, placed frames."""
        history = self.sharpness[-30:]
        if len(history) < 5:
            return False
        return pf.sharpness < self.options.blur_ratio * float(np.median(history))

    def _candidates(self, predicted: Similarity, count: int, radius_mm: float, latest: int | None = None) -> list[int]:
        """Return placed frames near the prediction: the latest (or `latest`) first, then the nearest, older ones
        mixed in."""
        if not self.order:
            return []
        latest = self.order[-1] if latest is None else latest
        described = [i for i in self.order if i in self.features]  # the keyframes: tracked frames have no features
        placed = np.array(described)
        centres = np.array([self.poses[i].t for i in described])
        dist = np.abs(centres - predicted.t)
        near = placed[dist < radius_mm]
        near_dist = dist[dist < radius_mm]
        ranked = [int(i) for i in near[np.argsort(near_dist)] if i != latest]
        recent = [i for i in ranked if latest - i <= self.options.loop_gap]
        old = [i for i in ranked if latest - i > self.options.loop_gap]
        chosen = [latest]
        # alternate recent and old so a revisit always gets a chance to close the loop
        while len(chosen) < count and (recent or old):
            for pool in (old, recent):
                if pool and len(chosen) < count:
                    chosen.append(pool.pop(0))
        return chosen

    def _match(self, pf: FrameEvidence, train: Features, min_inliers: int | None = None) -> SimilarityFit | None:
        """Return the similarity from the frame's mm to the train features' mm, or None on weak evidence."""
        return self._verify(pf, self._matched(pf, train), min_inliers, self.options.ransac_px)

    def _matched(self, pf: FrameEvidence, train: Features) -> tuple[np.ndarray, np.ndarray]:
        """Return the frame's and the train features' points (mm) their descriptors match (ratio test)."""
        iq, it = match_features(pf.features, train, self.options.ratio, same_point=SAME_PLACE_PX / self.px_per_mm)
        return pf.features.points[iq], train.points[it]

    def _verify(
        self, pf: FrameEvidence, matched: tuple[np.ndarray, np.ndarray], min_inliers: int | None, ransac_px: float
    ) -> SimilarityFit | None:
        """Return the RANSAC similarity of matched points at a gate of ransac_px pixels, or None on weak evidence."""
        return estimate_similarity(
            *matched,
            ransac_px / self.px_per_mm,
            seed=pf.index,
            min_inliers=self.options.min_inliers if min_inliers is None else min_inliers,
            dedupe_radius=SAME_PLACE_PX / self.px_per_mm,
            drag_gate=NEAR_PAIR_GATES if self.options.drag_reselect else self.options.drag_pair_gate,
        )

    def _confirmed_min_inliers(self) -> int:
        """Return the unique inliers a match to an older frame needs when the latest frame's match confirms it."""
        return max(3, round(self.options.min_inliers * self.options.confirmed_inlier_share))

    def _pairwise(self, pf: FrameEvidence, other: int, min_inliers: int | None = None) -> Match | None:
        if other not in self.features:  # a tracked frame: matched through its keyframe only
            return None
        fit = self._match(pf, self.features[other], min_inliers)
        return None if fit is None else feature_match(fit)

    def _older(self, pf: FrameEvidence, other: int, min_inliers: int | None) -> Match | None:
        """Return the match to an older keyframe at the RANSAC gate; when that falls short of options.min_inliers,
        the scan's skin is dragged (drag_evident) and the newest frame travels against `other` (two rows of a
        raster: dragged opposite ways), the match at options.loop_ransac_px's looser gate if it holds
        options.min_inliers in full (0: off). The descriptors are matched once for both gates."""
        if other not in self.features:  # a tracked frame: matched through its keyframe only
            return None
        matched = self._matched(pf, self.features[other])
        fit = self._verify(pf, matched, min_inliers, self.options.ransac_px)
        full = self.options.min_inliers
        looser = self.options.loop_ransac_px > 0 and self.drag_evident and (fit is None or fit.inliers < full)
        if looser and self._opposite(other):
            loose = self._verify(pf, matched, min_inliers, self.options.loop_ransac_px)
            if loose is not None and loose.inliers >= full:
                return feature_match(loose)
        if self.options.loop_drag_match and (fit is None or fit.inliers < full) and self._opposite(other):
            drag = self.corrections.drag_fit
            dragged = estimate_dragged_match(
                *matched,
                self.options.ransac_px / self.px_per_mm,
                drag.width_mm if drag is not None and drag.kept else DRAG_MATCH_WIDTH_MM,
                seed=pf.index,
                min_inliers=full,
                dedupe_radius=SAME_PLACE_PX / self.px_per_mm,
            )
            if dragged is not None and (self.drag_evident or self._dragged_along_travel(dragged, other)):
                return feature_match(dragged.fit)
        return None if fit is None else feature_match(fit)

    def _dragged_along_travel(self, match: DraggedMatch, other: int) -> bool:
        """Return whether both drags a match fitted lie along their frame's travel (physics.drag.along_travel) by at
        least DRAG_MATCH_MIN_MM: a skin dragged by the window, not a tissue's own deformation the model also
        absorbs."""
        newest = self.order[-1]
        for drag, frame in ((match.drag_src_mm, newest), (match.drag_dst_mm, other)):
            step = step_of_travel(self.order, self.poses, self.order.index(frame)) / self.poses[frame].a
            if abs(drag) < DRAG_MATCH_MIN_MM or not along_travel(drag, step):
                return False
        return True

    def _opposite(self, other: int) -> bool:
        """Return whether the newest frame travels against placed frame `other` (two rows of a raster)."""
        newest = step_of_travel(self.order, self.poses, len(self.order) - 1)
        return (newest * step_of_travel(self.order, self.poses, self.order.index(other)).conjugate()).real < 0

    def _mosaic_match(self, pf: PreparedFrame, predicted: Similarity, lost_for: int) -> tuple[Similarity, int] | None:
        """Match against the mosaic's features around the prediction (the paper's registration)."""
        near = self._candidates(predicted, 6, self._search_radius_mm(lost_for))
        pts = [self.poses[i].apply(self.features[i].points) for i in near]
        desc = [self.features[i].descriptors for i in near]
        if not pts:
            return None
        train = Features(np.concatenate(pts), np.concatenate(desc), np.zeros(sum(len(p) for p in pts)))
        fit = self._match(pf, train)
        return None if fit is None else (fit.transform, fit.inliers)

    def _search_radius_mm(self, lost_for: int = 0) -> float:
        """Return how far (mm) from a frame's centre placed frames are searched for a match, `lost_for` frames
        after the last placed one (SEARCH_RADIUS_WINDOWS)."""
        return SEARCH_RADIUS_WINDOWS * self.window_radius_mm * (1 + lost_for)

    def _plausible(self, pose: Similarity, predicted: Similarity, lost_for: int) -> bool:
        if len(self.order) < 2:  # no velocity yet: anything the window could still overlap
            return abs(pose.t - predicted.t) < 2 * self.window_radius_mm
        limit = self.options.max_jump_mm * (1 + lost_for)
        return abs(pose.t - predicted.t) <= limit and abs(np.angle(pose.a / predicted.a)) <= np.radians(25)

    def add(self, pf: PreparedFrame) -> FrameResult:
        """Return the result of registering one prepared frame: its status, pose and which earlier frames moved."""
        pf = self.describe(pf)
        self.corrections.record(pf)
        blurred = self._is_blurred(pf)
        if not self.order:
            return self._accept(pf, IDENTITY, [], len(pf.features), blurred)
        predicted = self.predict(pf.t_s)
        assert predicted is not None
        lost_for = pf.index - self.order[-1] - 1
        kind = self.options.registration
        if kind == "previous":
            found = self._pairwise(pf, self.order[-1])
            if found is None:
                return self._fail(pf, blurred, REASON_FEW_INLIERS)
            pose = self.poses[self.order[-1]].compose(found.relative.rigid())
            return self._accept(pf, pose, [], found.inliers, blurred)
        if kind == "mosaic":
            found_m = self._mosaic_match(pf, predicted, lost_for)
            if found_m is None:
                return self._fail(pf, blurred, REASON_FEW_INLIERS)
            pose, n = found_m
            pose = pose.rigid()
            reach = 2 * self.window_radius_mm * (1 + lost_for)  # the paper checks no motion model: only overlap
            if abs(pose.t - self.poses[self.order[-1]].t) > reach:
                return self._reject(pf, STATUS_REJECTED, blurred, REASON_IMPLAUSIBLE)
            return self._accept(pf, pose, [], n, blurred)
        return self._add_keyframes(pf, predicted, lost_for, blurred)

    def describe(self, pf: PreparedFrame) -> PreparedFrame:
        """Return the frame with its features (frame_prep.describe_frame): a keyframe, or a frame to relocalise."""
        return describe_frame(pf, self.options, self.centre_px, self.px_per_mm)

    def keyframe(self) -> int | None:
        """Return the newest placed frame with features (a keyframe) of the current run, or None."""
        for i in reversed(self.order):
            if i < self.run_start:
                return None
            if i in self.features:
                return i
        return None

    def track(self, pf: PreparedFrame) -> FrameResult | None:
        """Return the result of a frame tracked on the newest keyframe, or None when it must be a keyframe.

        Tracking (issue 32, after SVO's sparse image alignment): the frame's vein map is aligned directly onto the
        keyframe's from the motion prediction, with no features. The frame is placed by that one edge when the
        alignment's correlation reaches options.track_correlation and the frame still covers options.track_overlap
        of the keyframe's window; otherwise (or after lost frames, a blurred frame, MAX_TRACKED_RUN frames) it is a
        keyframe: described, matched against the keyframes around it, loops closed (add).
        """
        overlap = self.track_overlap(pf)
        if overlap <= 0 or len(self.order) < FIRST_KEYFRAMES:
            return None
        if pf.index - self.order[-1] != 1:  # frames lost in between: no motion to track from
            return None
        kf = self.keyframe()
        if kf is None or pf.index - kf > MAX_TRACKED_RUN or self._is_blurred(pf):
            return None
        predicted = self.predict(pf.t_s)
        assert predicted is not None
        found = self._tracking_match(pf, kf, self.poses[kf].inverse().compose(predicted), overlap)
        if found is None or not self._plausible(self.poses[kf].compose(found.relative), predicted, 0):
            return None
        self.corrections.record(pf)
        edges = [self._edge(pf, kf, found), *self._tracked_closures(pf, self.poses[kf].compose(found.relative), kf)]
        pose = place_node(self.poses, self.corrections.undeformed(edges, self.poses), pf.index)
        return self._refined(self._accept(pf, pose, edges, 0, False), edges)

    def track_overlap(self, pf: PreparedFrame) -> float:
        """Return the share of its keyframe's window a frame must cover to be tracked (0: it is a keyframe):
        options.track_overlap when the method tracks frames, else options.track_overlap_behind for a frame prepared
        without features (a live session behind its uploads: frame_prep.leaves_features)."""
        if tracks_frames(self.options):
            return self.options.track_overlap
        if pf.features is None and tracks_when_behind(self.options):
            return self.options.track_overlap_behind
        return 0.0

    def _tracking_match(self, pf: PreparedFrame, other: int, start: Similarity, overlap: float) -> Match | None:
        """Return the direct alignment of a frame on placed frame `other` from `start` (frame mm -> other mm) as a
        match with its affine and overlap pairs, or None below options.track_correlation or `overlap` (a share of
        other's window)."""
        return self._sparse_match(pf, other, start, self.options.track_correlation, overlap)

    def _sparse_match(
        self, pf: PreparedFrame, other: int, start: Similarity, min_correlation: float, min_overlap: float
    ) -> Match | None:
        """Return the sparse alignment of a frame on placed frame `other` from `start` (frame mm -> other mm) as a
        match with its affine and overlap pairs, or None below min_correlation or min_overlap (a share of other's
        window)."""
        template = self._template(other)
        fixed, moving = template.image, self._alignment(pf.index, pf)
        fit = sparse_align(template, moving, start)
        if fit is None or fit.affine is None or fit.correlation < min_correlation or fit.overlap < min_overlap:
            return None
        pairs = overlap_pairs(fixed, moving, fit.affine, TRACK_PAIR_STEP_PX)
        return Match(fit.transform, 0, self._direct_rms(fit), fit.affine, pairs=pairs)

    def _template(self, index: int) -> SparseTemplate:
        """Return a placed frame's sparse template (the newest TEMPLATE_CACHE used are kept)."""
        template = self._templates.pop(index, None)
        if template is None:
            template = sparse_template(self._alignment(index))
        self._templates[index] = template  # re-inserted: the dict's order is the order of use
        while len(self._templates) > TEMPLATE_CACHE:
            del self._templates[next(iter(self._templates))]
        return template

    def _tracked_closures(self, pf: PreparedFrame, pose: Similarity, kf: int) -> list[Edge]:
        """Return a tracked frame's loop closures: its sparse alignments, from its tracked pose, on the older
        keyframes around it (more than loop_gap frames before its keyframe; at most options.track_closures), each
        agreeing with the tracked pose within LOOP_GATE_MM and overlapping TRACK_CLOSURE_OVERLAP of their window."""
        edges: list[Edge] = []
        if self.options.track_closures <= 0:
            return edges
        for other in self._candidates(pose, self.options.neighbours, self._search_radius_mm(), kf)[1:]:
            if kf - other <= self.options.loop_gap:
                continue  # the keyframe's own neighbours: no loop
            start = self.poses[other].inverse().compose(pose)
            found = self._sparse_match(pf, other, start, self.options.min_correlation, TRACK_CLOSURE_OVERLAP)
            if found is None or abs(self.poses[other].compose(found.relative).t - pose.t) > LOOP_GATE_MM:
                continue
            edges.append(self._edge(pf, other, found))
            if len(edges) >= self.options.track_closures:
                break
        return edges

    def _alignment(self, index: int, pf: PreparedFrame | None = None) -> AlignmentImage:
        """Return the direct-alignment pyramid of a frame (placed ones cached, the latest few only)."""
        cached = self._pyramids.get(index)
        if cached is not None:
            return cached
        if pf is not None:
            vein, mask, scale = pf.vein, pf.vein_mask, _vein_scale(pf)
        else:
            vein, bits, scale = self.veins[index]
            mask = (np.unpackbits(bits, count=vein.size).reshape(vein.shape) * np.uint8(255)).astype(np.uint8)
        pyramid = alignment_image(vein, mask, self.centre_px, self.px_per_mm, scale)
        self._pyramids[index] = pyramid
        while len(self._pyramids) > ALIGNMENT_CACHE:
            del self._pyramids[min(self._pyramids)]
        return pyramid

    def _direct(self, pf: PreparedFrame, other: int, starts: list[Similarity], recentre: bool) -> DirectFit | None:
        """Return the best accepted direct alignment of the frame onto a placed one (frame mm -> other's mm)."""
        moving = self._alignment(pf.index, pf)
        fixed = self._alignment(other)
        best: DirectFit | None = None
        for start in starts:
            fit = align(fixed, moving, start, recentre=recentre)
            if fit is None or fit.correlation < self.options.min_correlation or fit.overlap < MIN_DIRECT_OVERLAP:
                continue
            if best is None or fit.correlation > best.correlation:
                best = fit
        return best

    def relocate(self, pf: PreparedFrame, other: int, match: Match) -> FrameResult:
        """Return the result of registering a frame relocalised on placed frame `other` (match: frame mm -> other mm).

        The frame is registered as any other (matched against `other` and the placed frames near it), with the
        relocalisation's match standing for the match to the latest frame; it starts a new run (no velocity).
        """
        self.corrections.record(pf)
        self.run_start = pf.index
        predicted = self.poses[other].compose(match.relative)
        return self._add_keyframes(pf, predicted, 0, self._is_blurred(pf), latest=other, found=match)

    def _add_keyframes(
        self,
        pf: PreparedFrame,
        predicted: Similarity,
        lost_for: int,
        blurred: bool,
        latest: int | None = None,
        found: Match | None = None,
    ) -> FrameResult:
        if latest is None:  # the newest frame, or the newest keyframe when that one was tracked (no features)
            newest_keyframe = self.keyframe()
            latest = self.order[-1] if self.order[-1] in self.features or newest_keyframe is None else newest_keyframe
        edges: list[Edge] = []
        anchor: Similarity | None = None
        found = self._pairwise(pf, latest) if found is None else found
        if found is not None and self.options.direct_refine:
            refined = self._direct(pf, latest, [found.relative], recentre=False)
            if refined is not None:
                pairs, drag_pairs = found.pairs, found.drag_pairs
                found = Match(refined.transform, found.inliers, found.rms, pairs=pairs, drag_pairs=drag_pairs)
        if found is None and self.options.direct_fallback:
            found = self._fallback(pf, latest, predicted)
        if found is not None:
            pose = self.poses[latest].compose(found.relative)
            if abs(pose.t - self.poses[latest].t) < 2 * self.window_radius_mm:  # the frames can overlap
                anchor = pose
                edges.append(self._edge(pf, latest, found))
        centre = anchor if anchor is not None else predicted
        radius = self._search_radius_mm(lost_for if anchor is None else 0)
        count = self.options.neighbours + (4 if anchor is None else 0)
        weak: list[Edge] = []
        for other in self._candidates(centre, count, radius, latest)[1:]:
            # agreeing with the match to the latest frame (LOOP_GATE_MM below) is evidence in itself: an anchored
            # match needs a share of the inliers (options.confirmed_inlier_share). Such a weak edge is kept only
            # when no other frame matched in full: it ties a hard scan's row to the row before where nothing else
            # does, and adds no noisier scale where full edges are (on simulated raster and short it cost up to
            # 0.1 mm when always kept)
            found = self._older(pf, other, self._confirmed_min_inliers() if anchor is not None else None)
            if found is None:
                continue
            pose = self.poses[other].compose(found.relative)
            if anchor is not None and abs(pose.t - anchor.t) > LOOP_GATE_MM:
                continue  # disagrees with the direct match to the latest frame: a false loop closure
            if anchor is None and not self._plausible(pose, predicted, lost_for):
                continue
            edge = self._edge(pf, other, found)
            (edges if found.inliers >= self.options.min_inliers else weak).append(edge)
        if len(edges) == int(anchor is not None):  # nothing but the latest frame matched in full: take the weak ones
            edges.extend(weak)
        if not edges:
            return self._fail(pf, blurred, self._why_not(pf))
        pose = place_node(self.poses, self.corrections.undeformed(edges, self.poses), pf.index)
        return self._refined(self._accept(pf, pose, edges, sum(e.inliers for e in edges), blurred), edges)

    def _refined(self, result: FrameResult, edges: list[Edge]) -> FrameResult:
        """Return a placed frame's result, with the frames a refinement moved when its edges' loops make one due
        (options.refine_every loop-closing frames since the last)."""
        if any(e.loop for e in edges):
            self.loops_since_refine += 1
        if self.options.refine and self.loops_since_refine >= self.options.refine_every:
            return FrameResult(result.index, result.status, result.pose, result.inliers, result.blurred, self.refine())
        return result

    def _fallback(self, pf: PreparedFrame, latest: int, predicted: Similarity) -> Match | None:
        """Return the best-correlated placement on the latest frame when features fail the inlier rule, or None.

        Candidates: direct alignment of the vein maps from the motion prediction and from "no motion" (a turn),
        and a feature match with half the minimum inliers or more, both as it is and as a start for direct
        alignment. Fewer inliers than the rule asks for can still be right (frames under heavy load share fewer
        keypoints), and vein maps can correlate best slightly off (on a simulated hard scan two frames at 30 N
        did 1 deg off, where 13 inliers were 0.01 deg off): the vein maps' correlation arbitrates.
        """
        to_latest = self.poses[latest].inverse()
        starts = [to_latest.compose(predicted), Similarity(predicted.a / self.poses[latest].a, 0j)]
        best = self._direct(pf, latest, starts, recentre=True)
        weak = None
        if latest in self.features:
            weak = self._match(pf, self.features[latest], max(3, self.options.min_inliers // 2))
        if weak is not None:
            refined = self._direct(pf, latest, [weak.transform], recentre=False)
            if refined is not None and (best is None or refined.correlation > best.correlation):
                best = refined
            corr, overlap = correlation(self._alignment(latest), self._alignment(pf.index, pf), weak.transform)
            ok = corr >= self.options.min_correlation and overlap >= MIN_DIRECT_OVERLAP
            if ok and (best is None or corr >= best.correlation):
                return feature_match(weak)
        return None if best is None else Match(best.transform, 0, self._direct_rms(best))

    def _direct_rms(self, fit: DirectFit) -> float:
        """Return an RMS-equivalent residual (mm) of a direct alignment, for its edge's sigma."""
        return DIRECT_SIGMA_MM + DIRECT_SIGMA_PER_DECORRELATION_MM * (1.0 - fit.correlation)

    def _why_not(self, pf: PreparedFrame) -> str:
        """Return why a frame that produced no edge was not placed (few keypoints, low correlation, few inliers)."""
        if len(pf.features) < self.options.min_inliers:
            return REASON_FEW_KEYPOINTS
        return REASON_LOW_CORRELATION if self.options.direct_fallback else REASON_FEW_INLIERS

    def _edge(self, pf: FrameEvidence, other: int, match: Match) -> Edge:
        """Return the pose-graph edge of a match, its sigma from the evidence and the loads (heavier = looser).

        A feature edge's sigma is its RMS residual over sqrt(inliers); a direct edge (inliers 0) carries an
        RMS-equivalent from its correlation (see _direct_rms), measured against feature edges on the shared scans.
        """
        load = 1.0 + 10.0 * max(pf.stretch, self.stretches[other])
        rms, inliers = match.rms, match.inliers
        sigma = (0.01 + (rms / np.sqrt(inliers) if inliers > 0 else rms)) * load
        loop = self.order[-1] - other > self.options.loop_gap
        return Edge(
            other,
            pf.index,
            match.relative,
            sigma,
            loop,
            inliers,
            affine=match.affine,
            affine_sigma=match.affine_sigma,
            view_affine=match.view_affine,
            centre=match.centre,
            lever_mm=match.spread_mm,
            pairs=match.pairs,
            drag_pairs=match.drag_pairs,
        )

    def refine(self, final: bool = False) -> tuple[int, ...]:
        """Return the frames that moved (> refinement.MOVED_MM) when re-optimising the placed poses on the pose graph.

        Global (every pose; the drag refitted at the end, the view model once its evidence grew by
        VIEW_REFIT_GROWTH and at the end) or local around the newest frame, as refinement.is_global decides.
        """
        self.loops_since_refine = 0
        if len(self.order) < 3 or not self.edges:
            return ()
        n = len(self.order)
        if not is_global(n, self.last_global_refine, final):
            return self._optimise(*local_pass(self.order, self.poses, self.edges, self.window_radius_mm))
        self.last_global_refine = n
        if final and self.options.fit_drag:
            self.corrections.fit_drag(self.edges, self.order, self.poses)
        elif self.options.fit_drag and self.options.loop_ransac_px > 0 and not self.drag_evident:
            recent = self.edges[-DRAG_CHECK_EDGES:]
            self.drag_evident = self.corrections.drag_evident(recent, self.order, self.poses)
        if self.options.fit_tilt and (
            final or view_evidence(self.edges) >= VIEW_REFIT_GROWTH * self.corrections.last_view_evidence
        ):
            self.corrections.fit_tilt(self.edges, self.poses, self.options.tissue_axis)
        band = 0.0 if final else self.options.chain_scale_band  # the final pass: every scale on the edges alone
        return self._optimise(self.poses, self.edges, {self.order[0]}, band=band)

    def refine_scales(self, targets: dict[int, float], sigma: float) -> tuple[int, ...]:
        """Return the frames that moved when re-optimising every pose, each frame's scale |a| held to its target
        with relative sigma `sigma`, frame 0 set to its own and held (refinement.scale_pass)."""
        start, priors = scale_pass(self.order, self.poses, targets, sigma)
        return self._optimise(start, self.edges, {self.order[0]}, priors)

    def _optimise(
        self,
        poses: dict[int, Similarity],
        edges: list[Edge],
        held: set[int],
        scale_priors: dict[int, tuple[float, float]] | None = None,
        band: float = 0.0,
    ) -> tuple[int, ...]:
        """Optimise `poses` on `edges` (undeformed) with `held` fixed; update them; return the frames that moved.

        band > 0 (MethodOptions.chain_scale_band, a global pass while the scan goes on): when the free frames' mean
        scale comes out beyond exp(+-band) of 1, the solve is repeated with that mean held at the band's edge
        (pose_graph's mean_scale, MEAN_SCALE_SIGMA). The graph's residuals shrink with the scale of the whole map,
        so edges that disagree (a skin dragged along, its stretch not undone until the end) pulled every frame but
        frame 0 toward scale 0, a few per cent a pass, until frame 0's own edges were dropped as outliers and it
        was left 31 mm from the rest (the simulated dragged raster, seed 4; docs/accuracy.md, "Skin drag").
        """
        undeformed = self.corrections.undeformed(edges, self.poses)
        solution = optimise_poses(poses, undeformed, fixed=held, scale_priors=scale_priors)
        scales = [abs(p.a) for i, p in solution.poses.items() if i not in held] if band > 0 else []
        if scales:
            mean = float(np.mean(scales))
            edge = float(np.clip(mean, np.exp(-band), np.exp(band)))
            if edge != mean:
                solution = optimise_poses(
                    poses, undeformed, fixed=held, scale_priors=scale_priors, mean_scale=(edge, MEAN_SCALE_SIGMA)
                )
        moved = moved_frames(solution.poses, self.poses)
        self.poses.update(solution.poses)
        return moved

    def _accept(
        self, pf: PreparedFrame, pose: Similarity, edges: list[Edge], inliers: int, blurred: bool
    ) -> FrameResult:
        if self.order:  # not frame 0, the map's origin and scale
            pose = banded_scale(pose, self.options.chain_scale_band)
        self.poses[pf.index] = pose
        if pf.features is not None:  # a keyframe (tracked frames are matched through their keyframe)
            self.features[pf.index] = pf.features
        self.times[pf.index] = pf.t_s
        self.stretches[pf.index] = pf.stretch
        self.corrections.loads[pf.index] = pf.load.fz_n
        self.edges.extend(edges)
        self.order.append(pf.index)
        self.veins[pf.index] = (pf.vein, np.packbits(pf.vein_mask > 0), _vein_scale(pf))
        if not blurred:  # only sharp, placed frames set the reference (noise frames would inflate it)
            self.sharpness.append(pf.sharpness)
        return FrameResult(pf.index, STATUS_OK, pose, inliers, blurred)

    def _fail(self, pf: PreparedFrame, blurred: bool, reason: str) -> FrameResult:
        """Return the result of a frame that could not be registered: a blurred one is rejected, else lost."""
        if blurred:
            return self._reject(pf, STATUS_REJECTED, blurred, REASON_BLUR)
        return self._reject(pf, STATUS_LOST, blurred, reason)

    def _reject(self, pf: PreparedFrame, status: str, blurred: bool, reason: str) -> FrameResult:
        return FrameResult(pf.index, status, None, 0, blurred, reason=reason)


def banded_scale(pose: Similarity, band: float) -> Similarity:
    """Return the pose with its scale |a| brought within exp(+-band) of 1 (its turn and translation kept), or the
    pose itself when it is within or band is 0 (MethodOptions.chain_scale_band)."""
    scale = abs(pose.a)
    if band <= 0 or scale <= 0:
        return pose
    held = float(np.clip(scale, np.exp(-band), np.exp(band)))
    return pose if held == scale else Similarity(pose.a * (held / scale), pose.t)
