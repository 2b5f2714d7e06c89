"""The reconstruction methods compared in the benchmark, as frozen option sets."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

METHOD_NAMES = ("sift-chain", "paper", "best")
REGISTRATION_KINDS = ("previous", "mosaic", "keyframes")


@dataclass(frozen=True)
class MethodOptions:
    """Options of one reconstruction method; units in each field's comment."""

    name: str
    rectify: bool = True  # spec §2 force rectification (else lens undistortion only)
    features: str = "sift"  # sift | modified-asift | asift
    max_features: int = 1000  # SIFT cap per view (0 = no cap); ignored when target_features > 0
    enhance: bool = True  # detect features on the vein map (the paper's segmentation step), not raw grey levels
    vein_scale: float = 0.5  # vein map and its features at this fraction of full resolution (0.5: 0.25 mm/px)
    target_features: int = 500  # adaptive detection: keypoints kept per frame, spread over it (0 = fixed thresholds)
    contrast_threshold: float = 0.03  # SIFT contrast threshold when target_features is 0
    sift_finest_octave: int = -1  # SIFT's finest octave: -1 OpenCV's doubled image, 0 the image's own pixels
    direct_fallback: bool = True  # when features fail, align the vein maps directly (phase correlation + ECC)
    direct_refine: bool = False  # refine every feature match to the latest frame by direct alignment
    min_correlation: float = 0.6  # ECC correlation of the vein maps for an accepted direct alignment
    registration: str = "keyframes"  # previous (frame-to-frame) | mosaic (paper) | keyframes (pose graph)
    # keyframes registration only: a frame is tracked (direct alignment on the newest keyframe, no features) while
    # it covers at least this share of the keyframe's window; below it, it becomes a keyframe (0: every frame is one)
    track_overlap: float = 0.0
    track_correlation: float = 0.6  # ... and while the tracking alignment's vein-map correlation reaches this
    # a live session behind its uploads (workers: track_lag_s) has its frames prepared without features: each is then
    # tracked as track_overlap would track it, at this overlap, or made a keyframe (0: every frame is a keyframe
    # however far behind). Offline nothing is behind: a reconstruction is track_overlap's alone (issue 32)
    track_overlap_behind: float = 0.85
    track_closures: int = 2  # a tracked frame's loop closures, by direct alignment on older keyframes (0: none)
    rigid_stitch: bool = False  # stitch with yaw + x/y only (the paper's correction) instead of the similarity
    # a placed frame whose window shows almost only skin this many stitched frames already cover is left out of the
    # mosaic (mosaic.stitch_cover; 0: every placed frame is stitched). A long examination passes over its skin
    # hundreds of times, and every frame stitched costs a paste live and again at the finish
    stitch_cover_cap: int = 16
    refine: bool = True  # global pose-graph refinement on loop closures (beyond the paper)
    self_calibrate: bool = True  # fit the tissue compliance from registration scales (beyond the paper)
    stiffening: bool = True  # let that fit's strain law stiffen with load when the scales show it
    scale_prior: float = 0.005  # at the end each frame's scale is held to that fit's law, this relative sigma (0: off)
    fit_tilt: bool = True  # learn the probe's true tilt (effective kappa) from the matches' affines; undo it
    fit_drag: bool = True  # learn the skin's friction drag under the sliding window from the matches; undo it
    # also try the tissue's anisotropy axis fixed in the tissue (turning against the probe's yaw), the scan's evidence
    # choosing: off by default, as on the simulated saturating cells the evidence chose it and the paths came out worse
    tissue_axis: bool = False
    flat_field: bool = True  # divide out the IR ring's vignetting before blending
    min_inliers: int = 20  # unique RANSAC inliers for an accepted registration
    confirmed_inlier_share: float = 0.5  # ... this share of it for a match to an older frame agreeing with the latest's
    ransac_px: float = 2.0  # RANSAC reprojection threshold, pixels of the rectified frame
    # once the scan's skin shows a drag, a keyframe's match to an older one travelled the opposite way that fails
    # ransac_px in full is tried again with this looser gate (pixels; 0: off). Skin dragged opposite ways on two rows
    # moves the overlap's centre by more than ransac_px against its rim: a raster loses most closures (issue 31)
    loop_ransac_px: float = 4.0
    # a keyframe's match to an older one travelled the opposite way that fails ransac_px in full is tried again with
    # its pairs gated about the skin's rest places, each frame's drag fitted (registration.drag_match): on the
    # simulated dragged rasters 9 -> 67 closures under the strongest drag, 303 -> 364 and 350 -> 404 on the milder
    # ones; no shared scan changes by more than 0.001 mm (issue 31, docs/accuracy.md "Skin drag")
    loop_drag_match: bool = True
    # each frame placed while the scan goes on has its pose's scale |a| held within exp(+-chain_scale_band) of 1,
    # what the calibration's law expects of a rectified frame (a tissue off the calibration, or loads of 30 N, stay
    # free): along a chain with few closures the scale no longer wanders away (a strong drag made it fall 0.2 % an
    # edge, to half over a raster, and no closure held: issue 31). 0.05 clamped a simulated hard scan's saturating
    # tissue (7.22 -> 7.82 mm), 0.12 let the dragged raster fall apart again. A global pass while the scan goes on
    # keeps the map's mean scale within the same band (registrar._optimise: disagreeing edges shrank a dragged
    # raster's whole map to half, seed 4: 31 -> 1.1 mm). The final pass re-optimises every scale on the edges alone
    # (0: off)
    chain_scale_band: float = 0.08
    # the skin drag's evidence (physics.drag): 0, a match's inliers; > 0, its pairs within this many RANSAC gates of
    # its similarity. The gate cuts the pairs a drag moves most (the window's centre), so the drags fitted to the
    # inliers come out smaller than the skin's (issue 31). 1.25 of 1.25, 1.5 and 2 tried: the one that turns no
    # shared scan further about frame 0 (docs/accuracy.md, "Skin drag")
    drag_pair_gate: float = 1.25
    # opt-in (issue 31): each match keeps its pairs within NEAR_PAIR_GATES gates; the drag is fitted to those within
    # drag_pair_gate gates of the undragged skin (one re-selection), and every edge undragged is re-measured on its
    # near pairs within one gate of the undragged skin: the gate about the dragged similarity leaves edges turned.
    # Off by default: it tipped clinical_veins_24's compliance law to linear (0.227 -> 0.373 mm)
    drag_reselect: bool = False
    # the skin drag's prior across each frame's travel (mm, 1 sigma; physics.drag): a window's friction drags the skin
    # along its stroke, so a drag turned across it is held to the gain's turn more tightly than along (0.6 mm, which
    # is isotropic). On the simulated dragged strokes the drags fitted came out turned up to 18 deg and 1.5x too large.
    # 0.15-0.6 tried (docs/accuracy.md, "Skin drag"): tighter helps strokes and costs raster s2 and clinical_veins_24
    drag_across_sigma_mm: float = 0.3
    ratio: float = 0.8  # Lowe ratio test
    neighbours: int = 4  # keyframes matched per frame (keyframes registration)
    loop_gap: int = 25  # an edge spanning more frames than this is a loop closure
    refine_every: int = 10  # re-optimise the pose graph after this many frames with loop closures
    max_jump_mm: float = 15.0  # a pose farther than this from the prediction is implausible
    blur_ratio: float = 0.35  # sharpness below this fraction of the running median = blurred frame

    def with_overrides(self, overrides: dict[str, Any]) -> MethodOptions:
        """Return a copy with overrides applied; unknown option names raise ValueError."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"unknown method option(s): {', '.join(unknown)}")
        return replace(self, **overrides)


def method_options(name: str) -> MethodOptions:
    """Return the options of a named method: sift-chain, paper or best."""
    if name == "sift-chain":
        return MethodOptions(
            name=name,
            rectify=False,
            registration="previous",
            rigid_stitch=True,
            stitch_cover_cap=0,
            refine=False,
            self_calibrate=False,
            fit_tilt=False,
            fit_drag=False,
            flat_field=False,
        )
    if name == "paper":
        return MethodOptions(
            name=name,
            features="modified-asift",
            max_features=400,
            registration="mosaic",
            rigid_stitch=True,
            stitch_cover_cap=0,
            refine=False,
            self_calibrate=False,
            fit_tilt=False,
            fit_drag=False,
            flat_field=False,
        )
    if name == "best":
        return MethodOptions(name=name)
    raise ValueError(f"unknown method {name!r}; expected one of {', '.join(METHOD_NAMES)}")
