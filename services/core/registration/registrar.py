"""Sequential registration of prepared frames against what is already placed (spec §2 "Pose").

Three strategies share one state machine: `previous` (frame-to-frame chaining, the SfM-like baseline),
`mosaic` (the paper: match against the features of the mosaic around the predicted position, keep yaw and
x/y), and `keyframes` (match against several overlapping placed frames, each match an edge of a similarity
pose graph; loop closures trigger a robust global re-optimisation).
"""

from __future__ import annotations

import cmath
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from services.core.methods import MethodOptions
from services.core.physics.drag import DragEvidence, DragFit, fit_drag, undragged_transforms
from services.core.physics.tissue_model import (
    AffineEvidence,
    HookeFit,
    ViewFit,
    corrected_relative,
    fit_kappa_to_tilts,
    fit_view_model,
)
from services.core.registration.direct_alignment import AlignmentImage, DirectFit, align, alignment_image, correlation
from services.core.registration.features import Features
from services.core.registration.frame_prep import PreparedFrame
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
from services.core.similarity import IDENTITY, Similarity

LOCAL_REFINE_FROM = 400  # placed frames: below this every refinement is global
GLOBAL_GROWTH = 1.25  # ... from it, a global pass when the placed frames grew by this factor since the last one
LOCAL_RADIUS_WINDOWS = 3.0  # a local pass frees the frames within this many window radii of the newest frame
LOCAL_RECENT = 60  # ... and the newest frames
LOCAL_MAX = 240  # ... at most this many of the nearest (an examination's passes pile frames on the same area)
# A global pass refits the view model only when the affine evidence grew by this factor since the last fit (and
# always at the end): fitting it at every global pass of a short scan cost 15 % of a live registering worker's
# time on a 336-frame raster; geometric refits cost a constant multiple of the last one
VIEW_REFIT_GROWTH = 1.25
# A match to an older frame that places the new frame farther than this from where the match to the latest frame
# places it is a false loop closure. It was max_jump_mm / 5 = 3 mm, which also refused true ones once a hard scan's
# chain had drifted 3 mm between passes: on simulated hard s1 / s2 no loop closed after frame 140, and the last
# rows drifted to 8.5 mm (path 2.32 / 3.79 mm; 1.79 / 3.08 mm at 6 mm, the same from 6 to 15 mm; the shared scans
# and the simulated raster, revisit and short cells unchanged). False matches land tens of mm away, and the pose
# graph's robust weights take the rest.
LOOP_GATE_MM = 6.0
MOVED_MM = 0.05  # a refined pose that moves a frame by less than this (0.4 px) does not re-render its tiles
MIN_DIRECT_OVERLAP = 0.15  # a direct alignment must overlap this share of the placed frame's window
DIRECT_SIGMA_MM = 0.05  # a direct edge's sigma at perfect correlation (about twice a feature edge's)
DIRECT_SIGMA_PER_DECORRELATION_MM = 1.0  # ... growing by this per unit of (1 - correlation)
DIRECTION_GAP = 3  # frames: a placed neighbour farther in the sequence is across a gap, not the way the probe went
STILL_MM = 0.3  # a frame whose neighbours are closer than this together has no direction of travel
ALIGNMENT_CACHE = 12  # placed frames whose alignment pyramids are kept (the latest ones: most often matched)


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
    separation_mm: Sequence[float] = (53.0, 53.0)  # the force sensors' S_X, S_Y (spec §2)
    kappa_prior_n_per_mm: float = 18.0  # the calibration's kappa: the prior of the fitted one
    compliance_per_n: float = 0.0  # the calibration's nu / (E A): the tissue anisotropy's unit
    poses: dict[int, Similarity] = field(default_factory=dict)
    features: dict[int, Features] = field(default_factory=dict)
    times: dict[int, float] = field(default_factory=dict)
    stretches: dict[int, float] = field(default_factory=dict)
    edges: list[Edge] = field(default_factory=list)
    sharpness: list[float] = field(default_factory=list)
    order: list[int] = field(default_factory=list)
    loops_since_refine: int = 0
    last_global_refine: int = 0  # placed frames at the last global refinement
    last_view_evidence: int = 0  # edges with affine evidence at the last view fit
    run_start: int = 0  # the first frame of the current run (placed after a landing or a relocalisation)
    # placed frames: vein map, its window mask bit-packed (np.packbits of mask > 0: 8x smaller), vein scale
    veins: dict[int, tuple[np.ndarray, np.ndarray, float]] = field(default_factory=dict)
    forces: dict[int, np.ndarray] = field(default_factory=dict)  # every frame seen: sensor forces F1..F4 (N)
    loads: dict[int, float] = field(default_factory=dict)  # placed frames: total load F_Z (N), the drag's prior
    imu_tilts: dict[int, np.ndarray] = field(default_factory=dict)  # frames with an IMU: its tilts (deg) then
    view_fit: ViewFit | None = None  # the probe's tilt and tissue anisotropy learned from the edges' affines
    kappa_reference: HookeFit | None = None  # kappa fitted to the IMU's tilts (the view fit's prior), if any
    drag_fit: DragFit | None = None  # the skin's friction drag learned from the edges' inlier pairs (at the end)
    _pyramids: dict[int, AlignmentImage] = field(default_factory=dict)
    _views: dict[int, np.ndarray] = field(default_factory=dict)  # each frame's view D under the current fit
    # each edge (by its frames) corrected under the current fit, with the edge it was corrected from
    _undeformed: dict[tuple[int, int], tuple[Edge, Edge]] = field(default_factory=dict)
    # each edge (by identity) undragged under the current drag fit, with the edge it was undragged from
    _undragged: dict[int, tuple[Edge, Edge]] = field(default_factory=dict)

    @property
    def ransac_mm(self) -> float:
        """Return the RANSAC threshold in mm."""
        return self.options.ransac_px / self.px_per_mm

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
        placed = np.array(self.order)
        centres = np.array([self.poses[i].t for i in self.order])
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
        same_place = 2.0 / self.px_per_mm
        iq, it = match_features(pf.features, train, self.options.ratio, same_point=same_place)
        return estimate_similarity(
            pf.features.points[iq],
            train.points[it],
            self.ransac_mm,
            seed=pf.index,
            min_inliers=self.options.min_inliers if min_inliers is None else min_inliers,
            dedupe_radius=same_place,
        )

    def _confirmed_min_inliers(self) -> int:
        """Return the unique inliers a match to an older frame needs when the latest frame's match confirms it."""
        return max(3, round(self.options.min_inliers * self.options.confirmed_inlier_share))

    def _pairwise(self, pf: FrameEvidence, other: int, min_inliers: int | None = None) -> Match | None:
        fit = self._match(pf, self.features[other], min_inliers)
        return None if fit is None else feature_match(fit)

    def _mosaic_match(self, pf: PreparedFrame, predicted: Similarity, lost_for: int) -> tuple[Similarity, int] | None:
        """Match against the mosaic's features around the prediction (the paper's registration)."""
        near = self._candidates(predicted, 6, 1.6 * self.window_radius_mm * (1 + lost_for))
        pts = [self.poses[i].apply(self.features[i].points) for i in near]
        desc = [self.features[i].descriptors for i in near]
        if not pts:
            return None
        train = Features(np.concatenate(pts), np.concatenate(desc), np.zeros(sum(len(p) for p in pts)))
        fit = self._match(pf, train)
        return None if fit is None else (fit.transform, fit.inliers)

    def _plausible(self, pose: Similarity, predicted: Similarity, lost_for: int) -> bool:
        if len(self.order) < 2:  # no velocity yet: anything the window could still overlap
            return abs(pose.t - predicted.t) < 2 * self.window_radius_mm
        limit = self.options.max_jump_mm * (1 + lost_for)
        return abs(pose.t - predicted.t) <= limit and abs(np.angle(pose.a / predicted.a)) <= np.radians(25)

    def add(self, pf: PreparedFrame) -> FrameResult:
        """Return the result of registering one prepared frame: its status, pose and which earlier frames moved."""
        self.forces[pf.index] = np.asarray(pf.forces_n, np.float64)  # its view, once the model is fitted
        if pf.imu_tilt_deg is not None:
            self.imu_tilts[pf.index] = np.asarray(pf.imu_tilt_deg, np.float64)
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
        self.forces[pf.index] = np.asarray(pf.forces_n, np.float64)
        if pf.imu_tilt_deg is not None:
            self.imu_tilts[pf.index] = np.asarray(pf.imu_tilt_deg, np.float64)
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
        latest = self.order[-1] if latest is None else latest
        edges: list[Edge] = []
        anchor: Similarity | None = None
        found = self._pairwise(pf, latest) if found is None else found
        if found is not None and self.options.direct_refine:
            refined = self._direct(pf, latest, [found.relative], recentre=False)
            if refined is not None:
                found = Match(refined.transform, found.inliers, found.rms, pairs=found.pairs)
        if found is None and self.options.direct_fallback:
            found = self._fallback(pf, latest, predicted)
        if found is not None:
            pose = self.poses[latest].compose(found.relative)
            if abs(pose.t - self.poses[latest].t) < 2 * self.window_radius_mm:  # the frames can overlap
                anchor = pose
                edges.append(self._edge(pf, latest, found))
        centre = anchor if anchor is not None else predicted
        radius = 1.6 * self.window_radius_mm * (1 + (lost_for if anchor is None else 0))
        count = self.options.neighbours + (4 if anchor is None else 0)
        weak: list[Edge] = []
        for other in self._candidates(centre, count, radius, latest)[1:]:
            # agreeing with the match to the latest frame (LOOP_GATE_MM below) is evidence in itself: an anchored
            # match needs a share of the inliers (options.confirmed_inlier_share). Such a weak edge is kept only
            # when no other frame matched in full: it ties a hard scan's row to the row before where nothing else
            # does, and adds no noisier scale where full edges are (on simulated raster and short it cost up to
            # 0.1 mm when always kept)
            found = self._pairwise(pf, other, self._confirmed_min_inliers() if anchor is not None else None)
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
        pose = place_node(self.poses, self.undeformed(edges), pf.index)
        total = sum(e.inliers for e in edges)
        result = self._accept(pf, pose, edges, total, blurred)
        if any(e.loop for e in edges):
            self.loops_since_refine += 1
        if self.options.refine and self.loops_since_refine >= self.options.refine_every:
            return FrameResult(pf.index, result.status, result.pose, total, blurred, self.refine())
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
        )

    def view(self, index: int) -> np.ndarray:
        """Return a frame's view D (observed mm = D undeformed mm) under the fitted view model (I before a fit)."""
        if self.view_fit is None or index not in self.forces:
            return np.eye(2)
        cached = self._views.get(index)
        if cached is None:
            pose = self.poses.get(index)
            if pose is None or pose.a == 0:  # not placed yet: its yaw (the tissue axis's turn) is not known
                return self.view_fit.model.views(self.forces[index], 0.0)
            cached = self.view_fit.model.views(self.forces[index], cmath.phase(pose.a))
            self._views[index] = cached
        return cached

    def undeformed(self, edges: list[Edge]) -> list[Edge]:
        """Return the edges measuring relative poses between undeformed frames (tilt foreshortening removed).

        Each edge is corrected once per view fit (cached by its frames until the next fit_tilt): a refinement
        re-reads hundreds of edges whose correction has not changed.
        """
        if self.view_fit is None and not self.dragged():
            return edges
        out = []
        for e in edges:
            cached = self._undeformed.get((e.i, e.j))
            if cached is None or cached[0] is not e:
                u = self.undragged(e)
                if self.view_fit is not None:
                    u = u.with_relative(corrected_relative(u.relative, u.affine, self.view(e.i), self.view(e.j)))
                cached = (e, u)
                self._undeformed[(e.i, e.j)] = cached
            out.append(cached[1])
        return out

    def undragged(self, e: Edge) -> Edge:
        """Return an edge between undragged frames (physics.drag), itself without a kept drag fit or inlier pairs.

        Made once per drag fit (the view fit and the pose graph both read it at the end: 30 000 edges over a
        4-minute examination).
        """
        fit = self.drag_fit
        if fit is None or not fit.kept or e.pairs is None:
            return e
        cached = self._undragged.get(id(e))
        if cached is None or cached[0] is not e:
            relative, (affine, view_affine) = undragged_transforms(
                e.relative, (e.affine, e.view_affine), e.pairs, fit.of(e.i), fit.of(e.j), fit.width_mm
            )
            cached = (e, replace(e, relative=relative, affine=affine, view_affine=view_affine))
            self._undragged[id(e)] = cached
        return cached[1]

    def fit_drag(self) -> DragFit | None:
        """Return the skin's drag fitted to every edge's inlier pairs (physics.drag), also kept as drag_fit."""
        evidence = [DragEvidence(e.i, e.j, e.pairs, e.relative.a) for e in self.edges if e.pairs is not None]
        self.drag_fit = fit_drag(evidence, self.loads, self.directions())
        self._undeformed = {}
        self._undragged = {}
        return self.drag_fit

    def dragged(self) -> bool:
        """Return whether a drag was learned and kept (physics.drag): the edges, path and mosaic undo it."""
        return self.drag_fit is not None and self.drag_fit.kept

    def directions(self) -> dict[int, complex]:
        """Return each placed frame's unit direction of travel in its own axes (0 when still or alone in its run)."""
        out: dict[int, complex] = {}
        order = self.order
        for k, i in enumerate(order):
            before = order[k - 1] if k > 0 and i - order[k - 1] <= DIRECTION_GAP else i
            after = order[k + 1] if k + 1 < len(order) and order[k + 1] - i <= DIRECTION_GAP else i
            step = self.poses[after].t - self.poses[before].t
            a = self.poses[i].a
            out[i] = (step / abs(step)) * (abs(a) / a) if abs(step) > STILL_MM and a != 0 else 0j
        return out

    def _view_evidence(self) -> int:
        """Return how many edges carry affine evidence for the view model."""
        return sum(1 for e in self.edges if e.view_affine is not None)

    def fit_tilt(self) -> ViewFit | None:
        """Return the view model (kappa, anisotropy) refitted from every edge's affine, else the previous one.

        The fit is services.core.physics.tissue_model's; None while no fit has succeeded yet.
        """
        undragged = (self.undragged(e) for e in self.edges if e.view_affine is not None)
        evidence = [AffineEvidence(e.i, e.j, e.view_affine, e.affine_sigma) for e in undragged]
        self.kappa_reference = self._kappa_from_imu()
        fit = fit_view_model(
            evidence,
            self.forces,
            self.separation_mm,
            self.kappa_prior_n_per_mm,
            self.compliance_per_n,
            reference=self.kappa_reference,
            yaw_rad={i: cmath.phase(p.a) for i, p in self.poses.items() if p.a != 0},
        )
        if fit is not None:
            self.view_fit = fit
            self.last_view_evidence = len(evidence)
            self._views = {}
            self._undeformed = {}
        return self.view_fit

    def _kappa_from_imu(self) -> HookeFit | None:
        """Return kappa fitted to the IMU's tilts of the frames seen (spec §2 calibration), or None (no IMU, or
        too little tilt: the images alone decide)."""
        if not self.imu_tilts:
            return None
        frames = sorted(self.imu_tilts)
        try:
            return fit_kappa_to_tilts(
                np.stack([self.imu_tilts[i] for i in frames]),
                np.stack([self.forces[i] for i in frames]),
                self.separation_mm,
            )
        except ValueError:
            return None

    def refine(self, final: bool = False) -> tuple[int, ...]:
        """Return the frames that moved (> MOVED_MM) when re-optimising the placed poses on the pose graph.

        Global (every pose; the view model refitted once its evidence grew by VIEW_REFIT_GROWTH, and at the end)
        while the scan is short, at the end (final), and
        whenever the placed frames grew by GLOBAL_GROWTH since the last global pass; in between a local pass
        around the newest frame (local_refine). So a minutes-long examination costs a bounded amount per loop
        closure, plus global passes whose total is a constant multiple of the last one (issue 15).
        """
        self.loops_since_refine = 0
        if len(self.order) < 3 or not self.edges:
            return ()
        n = len(self.order)
        if final or n < LOCAL_REFINE_FROM or n >= GLOBAL_GROWTH * self.last_global_refine:
            self.last_global_refine = n
            if final and self.options.fit_drag:
                self.fit_drag()
            if self.options.fit_tilt and (
                final or self._view_evidence() >= VIEW_REFIT_GROWTH * self.last_view_evidence
            ):
                self.fit_tilt()
            return self._optimise(self.poses, self.edges, {self.order[0]})
        return self.local_refine()

    def refine_scales(self, targets: dict[int, float], sigma: float) -> tuple[int, ...]:
        """Return the frames that moved when re-optimising every pose, each frame's scale |a| held to its target.

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
        first = self.order[0]
        start = dict(self.poses)
        if first in targets:  # the whole placement rescaled about frame 0 (at the origin), so the graph's weak
            ratio = targets[first] / abs(self.poses[first].a)  # pulls toward the start agree with frame 0's scale
            start = {i: Similarity(p.a * ratio, p.t * ratio) for i, p in self.poses.items()}
        priors = {i: (t, sigma * t) for i, t in targets.items() if i != first}
        solution = optimise_poses(start, self.undeformed(self.edges), {first}, scale_priors=priors)
        moved = tuple(i for i, p in solution.poses.items() if abs(p.t - self.poses[i].t) > MOVED_MM)
        self.poses.update(solution.poses)
        return moved

    def local_refine(self) -> tuple[int, ...]:
        """Return the frames that moved when re-optimising the poses near the newest frame.

        Near: the LOCAL_MAX nearest within LOCAL_RADIUS_WINDOWS window radii, and the newest LOCAL_RECENT frames;
        the frames they share edges with are held where they are. Its cost is bounded however long the scan
        (issue 15).
        """
        newest = self.poses[self.order[-1]].t
        reach = LOCAL_RADIUS_WINDOWS * self.window_radius_mm
        placed = np.array(self.order)
        dist = np.abs(np.array([self.poses[i].t for i in self.order]) - newest)
        near = np.flatnonzero(dist < reach)
        nearest = near[np.argsort(dist[near], kind="stable")[:LOCAL_MAX]]
        active = {int(i) for i in placed[nearest]} | set(self.order[-LOCAL_RECENT:])
        active.discard(self.order[0])
        edges = [e for e in self.edges if e.i in active or e.j in active]
        held = {e.i for e in edges if e.i not in active} | {e.j for e in edges if e.j not in active}
        if not held:
            held = {self.order[0]}
        return self._optimise({i: self.poses[i] for i in active | held}, edges, held)

    def _optimise(self, poses: dict[int, Similarity], edges: list[Edge], held: set[int]) -> tuple[int, ...]:
        """Optimise `poses` on `edges` (undeformed) with `held` fixed; update them; return the frames that moved."""
        solution = optimise_poses(poses, self.undeformed(edges), fixed=held)
        moved = tuple(i for i, p in solution.poses.items() if abs(p.t - self.poses[i].t) > MOVED_MM and i in self.poses)
        self.poses.update(solution.poses)
        return moved

    def _accept(
        self, pf: PreparedFrame, pose: Similarity, edges: list[Edge], inliers: int, blurred: bool
    ) -> FrameResult:
        self.poses[pf.index] = pose
        self.features[pf.index] = pf.features
        self.times[pf.index] = pf.t_s
        self.stretches[pf.index] = pf.stretch
        self.loads[pf.index] = pf.load.fz_n
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
