"""Synthetic feature matches between frames of a serpentine (3 rows of 12) whose skin is dragged by known amounts
(physics.drag's model): the drag tests' scan, shared by the drag fit's and the edge corrections' tests."""

from __future__ import annotations

import numpy as np

from services.core.physics.drag import DragEvidence, profile
from services.core.similarity import Similarity, lsq_similarity

WIDTH_MM = 15.0  # the true profile's width (one of the widths the fit tries)
STEP_MM = 4.0  # frames 4 mm apart along a row, as the shared rasters' 3.8 mm
NOISE_MM = 0.03  # feature localisation noise (a quarter pixel at 8 px/mm)


def rest_to_frame(rest: np.ndarray, pose: Similarity, drag: complex) -> np.ndarray:
    """Return the frame points (complex mm) that show skin resting at world points `rest` under a frame's drag."""
    q = (rest - pose.t) / pose.a  # undragged frame coordinates
    p = q.copy()
    for _ in range(30):  # p - D phi(p) = q, by fixed point (|D phi'| << 1)
        p = q + drag * profile(p, WIDTH_MM)
    return p


def dragged_serpentine(
    gain_mm_per_n: float, seed: int, turn_deg: float = 0.0, noise_mm: float = NOISE_MM
) -> tuple[list[DragEvidence], dict[int, float], dict[int, complex], dict]:
    """Return matches between 3 rows of 12 frames (a serpentine: the drag flips with the stroke), the loads, the
    directions of travel, and the truth (poses and drags); turn_deg turns every drag from the travel (0: along);
    noise_mm: each pair point's localisation noise (mm, 1 sigma per axis)."""
    rng = np.random.default_rng(seed)
    poses, drags, loads, directions = {}, {}, {}, {}
    k = 0
    for row in range(3):
        way = 1 if row % 2 == 0 else -1
        for col in range(12):
            x = (col if way > 0 else 11 - col) * STEP_MM
            poses[k] = Similarity(np.exp(1j * rng.normal(0, 0.01)), complex(x, 20.0 * row))
            loads[k] = float(rng.uniform(4.0, 16.0))
            directions[k] = complex(way, 0.0)
            drags[k] = gain_mm_per_n * loads[k] * way * rng.uniform(0.6, 1.0) * np.exp(1j * np.radians(turn_deg))
            k += 1
    evidence = []
    for i in poses:
        for j in poses:
            if j <= i or abs(poses[j].t - poses[i].t) > 28.0:
                continue
            centre = (poses[i].t + poses[j].t) / 2
            rest = centre + rng.uniform(-14, 14, 60) + 1j * rng.uniform(-9, 9, 60)
            pi = rest_to_frame(rest, poses[i], drags[i]) + np.array([1, 1j]) @ rng.normal(0, noise_mm, (2, 60))
            pj = rest_to_frame(rest, poses[j], drags[j]) + np.array([1, 1j]) @ rng.normal(0, noise_mm, (2, 60))
            pairs = np.stack([pj.real, pj.imag, pi.real, pi.imag], axis=1).astype(np.float32)
            evidence.append(DragEvidence(i, j, pairs, poses[j].a / poses[i].a))
    return evidence, loads, directions, {"poses": poses, "drags": drags}


def gated(ev: DragEvidence, gate_mm: float, near_gates: float) -> tuple[Similarity, np.ndarray, np.ndarray] | None:
    """Return a match as a RANSAC gate measures it: the least-squares similarity of its inliers (the pairs within
    gate_mm of the similarity of them all), the inliers, and the pairs within near_gates gates (none at 0); None
    below 8 inliers."""
    pj, pi = ev.pairs[:, 0] + 1j * ev.pairs[:, 1], ev.pairs[:, 2] + 1j * ev.pairs[:, 3]
    whole = lsq_similarity(pj, pi)
    off = np.abs(whole.a * pj + whole.t - pi)
    inliers = off < gate_mm
    if inliers.sum() < 8:
        return None
    return lsq_similarity(pj[inliers], pi[inliers]), ev.pairs[inliers], ev.pairs[off < near_gates * gate_mm]
