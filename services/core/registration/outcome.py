"""What registering a frame produces: its status and reason, the match it was placed by, and its result.

Shared by the registrar, the atlas of maps (services.core.registration.atlas) and the session that reports
them (path rows' status and reason, spec §4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from services.core.registration.features import Features
from services.core.registration.matching import SimilarityFit
from services.core.similarity import Similarity

STATUS_OK, STATUS_LOST, STATUS_REJECTED = "ok", "lost", "rejected"
# Why a frame was not placed (path.csv `reason`, the report, the session state); "" for placed frames.
REASON_FEW_KEYPOINTS = "few_keypoints"  # too little vein structure detected to match
REASON_FEW_INLIERS = "few_inliers"  # features matched, but too few agree on one transform
REASON_LOW_CORRELATION = "low_correlation"  # direct alignment did not reach the acceptance correlation
REASON_BLUR = "blur"  # a motion-blurred frame that could not be registered
REASON_IMPLAUSIBLE = "implausible_jump"  # a pose too far from the motion prediction
REASON_MISSING = "missing"  # the frame never arrived (declared lost by the queue)
REASON_BAD_FRAME = "bad_frame"  # the frame's content could not be processed (undecodable, wrong size)
REASON_NO_CONTACT = "no_contact"  # taken with the window off the skin (rejected; services.core.contact)
REASON_FRAGMENT = "unjoined_fragment"  # placed on a fragment that has not joined the map (atlas)
REASONS = (
    REASON_FEW_KEYPOINTS,
    REASON_FEW_INLIERS,
    REASON_LOW_CORRELATION,
    REASON_BLUR,
    REASON_IMPLAUSIBLE,
    REASON_MISSING,
    REASON_BAD_FRAME,
    REASON_NO_CONTACT,
    REASON_FRAGMENT,
)


class FrameEvidence(Protocol):
    """What matching a frame needs of it: its index, features (mm) and centre stretch (a PreparedFrame has them)."""

    @property
    def index(self) -> int: ...
    @property
    def features(self) -> Features: ...
    @property
    def stretch(self) -> float: ...


@dataclass(frozen=True)
class Match:
    """A frame registered on a placed one: the relative similarity (frame mm -> placed mm) and its evidence."""

    relative: Similarity
    inliers: int  # 0 for a direct alignment
    rms: float  # mm
    affine: np.ndarray | None = None  # the full affine of a feature match (2x3), see SimilarityFit
    affine_sigma: float = math.inf
    view_affine: np.ndarray | None = None  # the affine on its own inliers: the view model's evidence
    centre: complex = 0j  # where the match is measured (the inliers' centroid, frame mm); 0 for a direct one
    spread_mm: float = 0.0  # the inliers' RMS distance from it; 0: unknown (the pose graph's default lever)
    pairs: np.ndarray | None = None  # the feature inliers (n, 4: frame x, y, placed x, y; mm), see SimilarityFit
    drag_pairs: np.ndarray | None = None  # the skin drag's evidence (the same layout), see SimilarityFit


def feature_match(fit: SimilarityFit) -> Match:
    """Return the Match of a feature fit (with its full affine and where its inliers lie)."""
    return Match(
        fit.transform,
        fit.inliers,
        fit.rms,
        fit.affine,
        fit.affine_sigma,
        fit.view_affine,
        fit.centre,
        fit.spread,
        fit.pairs,
        fit.drag_pairs,
    )


@dataclass(frozen=True)
class FrameResult:
    """The outcome for one frame: status, pose (frame mm -> mosaic mm) or None, evidence, frames moved."""

    index: int
    status: str
    pose: Similarity | None
    inliers: int
    blurred: bool
    moved: tuple[int, ...] = ()
    reason: str = ""  # one of REASONS when status is not ok
