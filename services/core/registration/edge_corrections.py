"""The deformations a map's edges are corrected for: the view model and the skin's drag (spec §2 "Pose").

An edge measures the relative pose of two frames as the camera saw them: foreshortened by the probe's tilt and the
tissue's anisotropy under the load (the view model, physics.tissue_model), and shifted by the skin dragged under the
sliding window (physics.drag). Both are learned from the map's edges and the probe's forces; the pose graph reads
the edges with both undone.
"""

from __future__ import annotations

import cmath
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from services.core.physics.drag import (
    PRIOR_SIGMA_MM,
    RESELECT_ROUNDS,
    DragEvidence,
    DragFit,
    fit_drag,
    undragged_transforms,
)
from services.core.physics.tissue_model import (
    AffineEvidence,
    HookeFit,
    ViewFit,
    corrected_relative,
    fit_kappa_to_tilts,
    fit_view_model,
)
from services.core.registration.frame_prep import PreparedFrame
from services.core.registration.pose_graph import Edge
from services.core.similarity import Similarity

DIRECTION_GAP = 3  # frames: a placed neighbour farther in the sequence is across a gap, not the way the probe went
STILL_MM = 0.3  # a frame whose neighbours are closer than this together has no direction of travel
FILL_REACH = 12  # frames: a frame without drag evidence takes its fitted neighbours' drag within this reach


@dataclass(eq=False)
class EdgeCorrections:
    """A map's probe measurements, the view model and skin drag learned from them, and its edges corrected."""

    separation_mm: Sequence[float] = (53.0, 53.0)  # the force sensors' S_X, S_Y (spec §2)
    kappa_prior_n_per_mm: float = 18.0  # the calibration's kappa: the prior of the fitted one
    compliance_per_n: float = 0.0  # the calibration's nu / (E A): the tissue anisotropy's unit
    forces: dict[int, np.ndarray] = field(default_factory=dict)  # every frame seen: sensor forces F1..F4 (N)
    loads: dict[int, float] = field(default_factory=dict)  # placed frames: total load F_Z (N), the drag's prior
    imu_tilts: dict[int, np.ndarray] = field(default_factory=dict)  # frames with an IMU: its tilts (deg) then
    view_fit: ViewFit | None = None  # the probe's tilt and tissue anisotropy learned from the edges' affines
    kappa_reference: HookeFit | None = None  # kappa fitted to the IMU's tilts (the view fit's prior), if any
    # > 0 (MethodOptions.drag_reselect): the RANSAC gate (mm) about the undragged skin that the drag fit's pairs
    # (drag_pair_gates of it) and the undragged edges' pairs (one) are chosen within, from each edge's near pairs
    gate_mm: float = 0.0
    drag_pair_gates: float = 0.0
    drag_across_sigma_mm: float = PRIOR_SIGMA_MM  # the drag prior's sigma across the travel (physics.drag)
    drag_fit: DragFit | None = None  # the skin's friction drag learned from the edges' inlier pairs (at the end)
    last_view_evidence: int = 0  # edges with affine evidence at the last view fit
    _views: dict[int, np.ndarray] = field(default_factory=dict)  # each frame's view D under the current fit
    # each edge (by its frames) corrected under the current fit, with the edge it was corrected from
    _undeformed: dict[tuple[int, int], tuple[Edge, Edge]] = field(default_factory=dict)
    # each edge (by identity) undragged under the current drag fit, with the edge it was undragged from
    _undragged: dict[int, tuple[Edge, Edge]] = field(default_factory=dict)

    def record(self, pf: PreparedFrame) -> None:
        """Keep a frame's sensor forces (its view, once the model is fitted) and its IMU's tilts, if any."""
        self.forces[pf.index] = np.asarray(pf.forces_n, np.float64)
        if pf.imu_tilt_deg is not None:
            self.imu_tilts[pf.index] = np.asarray(pf.imu_tilt_deg, np.float64)

    def view(self, index: int, poses: dict[int, Similarity]) -> np.ndarray:
        """Return a frame's view D (observed mm = D undeformed mm) under the fitted view model (I before a fit)."""
        if self.view_fit is None or index not in self.forces:
            return np.eye(2)
        cached = self._views.get(index)
        if cached is None:
            pose = poses.get(index)
            placed = pose is not None and pose.a != 0
            if not placed and self.view_fit.model.anisotropy_axis == "tissue":  # its yaw, the axis's turn, unknown
                return self.view_fit.model.views(self.forces[index], 0.0)
            cached = self.view_fit.model.views(self.forces[index], cmath.phase(pose.a) if placed else 0.0)
            self._views[index] = cached
        return cached

    def undeformed(self, edges: list[Edge], poses: dict[int, Similarity]) -> list[Edge]:
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
                    views = self.view(e.i, poses), self.view(e.j, poses)
                    u = u.with_relative(corrected_relative(u.relative, u.affine, *views))
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
                e.relative,
                (e.affine, e.view_affine),
                e.pairs,
                fit.of(e.i),
                fit.of(e.j),
                fit.width_mm,
                e.drag_pairs,
                self.gate_mm,
            )
            cached = (e, replace(e, relative=relative, affine=affine, view_affine=view_affine))
            self._undragged[id(e)] = cached
        return cached[1]

    def fit_drag(self, edges: list[Edge], order: list[int], poses: dict[int, Similarity]) -> DragFit | None:
        """Return the skin's drag fitted to every edge's inlier pairs (physics.drag), also kept as drag_fit."""
        fit = self._drag(edges, order, poses)
        # frames without feature edges (tracked between keyframes) take their neighbours' drag
        self.drag_fit = None if fit is None else fit.filled(order, FILL_REACH)
        self._undeformed = {}
        self._undragged = {}
        return self.drag_fit

    def drag_evident(self, edges: list[Edge], order: list[int], poses: dict[int, Similarity]) -> bool:
        """Return whether the edges so far show the skin dragged (physics.drag keeps a fit), keeping nothing: while
        the scan goes on the drag is only detected, and undone at the end (fit_drag)."""
        fit = self._drag(edges, order, poses, reselect_rounds=0)  # detection alone: the first pass decides
        return fit is not None and fit.kept

    def _drag(
        self, edges: list[Edge], order: list[int], poses: dict[int, Similarity], reselect_rounds: int = RESELECT_ROUNDS
    ) -> DragFit | None:
        # a direct alignment's pairs (inliers 0) are sampled from its affine: no curvature to learn a drag from;
        # drag_pair_gate 0 fits the inliers alone, whatever near pairs drag_reselect keeps
        inliers_only = self.gate_mm > 0 and self.drag_pair_gates <= 0
        evidence = [
            DragEvidence(e.i, e.j, e.pairs if e.drag_pairs is None or inliers_only else e.drag_pairs, e.relative.a)
            for e in edges
            if e.pairs is not None and e.inliers
        ]
        return fit_drag(
            evidence,
            self.loads,
            directions_of_travel(order, poses),
            reselect_gate_mm=self.drag_pair_gates * self.gate_mm,
            reselect_rounds=reselect_rounds,
            across_sigma_mm=self.drag_across_sigma_mm,
        )

    def dragged(self) -> bool:
        """Return whether a drag was learned and kept (physics.drag): the edges, path and mosaic undo it."""
        return self.drag_fit is not None and self.drag_fit.kept

    def fit_tilt(self, edges: list[Edge], poses: dict[int, Similarity], tissue_axis: bool = False) -> ViewFit | None:
        """Return the view model (kappa, anisotropy) refitted from every edge's affine, else the previous one.

        The fit is services.core.physics.tissue_model's (with tissue_axis, the anisotropy's axis may also be fixed
        in the tissue: each frame's yaw is passed); None while no fit has succeeded yet.
        """
        undragged = (self.undragged(e) for e in edges if e.view_affine is not None)
        evidence = [AffineEvidence(e.i, e.j, e.view_affine, e.affine_sigma) for e in undragged]
        self.kappa_reference = self._kappa_from_imu()
        fit = fit_view_model(
            evidence,
            self.forces,
            self.separation_mm,
            self.kappa_prior_n_per_mm,
            self.compliance_per_n,
            reference=self.kappa_reference,
            yaw_rad={i: cmath.phase(p.a) for i, p in poses.items() if p.a != 0} if tissue_axis else None,
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


def view_evidence(edges: list[Edge]) -> int:
    """Return how many edges carry affine evidence for the view model."""
    return sum(1 for e in edges if e.view_affine is not None)


def step_of_travel(order: list[int], poses: dict[int, Similarity], k: int) -> complex:
    """Return the placed frame order[k]'s step of travel (map mm): between its placed neighbours in the sequence,
    each only within DIRECTION_GAP frames (0 when alone in its run: a lift or a gap is not the way it went)."""
    i = order[k]
    before = order[k - 1] if k > 0 and i - order[k - 1] <= DIRECTION_GAP else i
    after = order[k + 1] if k + 1 < len(order) and order[k + 1] - i <= DIRECTION_GAP else i
    return poses[after].t - poses[before].t


def directions_of_travel(order: list[int], poses: dict[int, Similarity]) -> dict[int, complex]:
    """Return each placed frame's unit direction of travel in its own axes (0 when still or alone in its run)."""
    out: dict[int, complex] = {}
    for k, i in enumerate(order):
        step = step_of_travel(order, poses, k)
        a = poses[i].a
        out[i] = (step / abs(step)) * (abs(a) / a) if abs(step) > STILL_MM and a != 0 else 0j
    return out
