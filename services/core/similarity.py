"""The 2-D similarity transform every pose, relative measurement and mosaic placement is expressed in, and the
least-squares similarity and affine of point pairs (a match's full affine, the drag's correction of them)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """A 2-D similarity p -> a p + t on complex coordinates (x + iy, image axes): a = s e^{i yaw}, t in mm."""

    a: complex
    t: complex

    @property
    def yaw_rad(self) -> float:
        """Return the rotation angle in radians (image axes, R the ordinary 2-D rotation matrix)."""
        return float(np.angle(self.a))

    @property
    def scale(self) -> float:
        """Return the scale factor |a| (dimensionless)."""
        return float(abs(self.a))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Return points (..., 2) mapped by the similarity (same units as t)."""
        z = points[..., 0] + 1j * points[..., 1]
        w = self.a * z + self.t
        return np.stack([w.real, w.imag], axis=-1)

    def compose(self, other: Similarity) -> Similarity:
        """Return self after other: p -> self(other(p))."""
        return Similarity(self.a * other.a, self.a * other.t + self.t)

    def inverse(self) -> Similarity:
        """Return the inverse similarity."""
        return Similarity(1.0 / self.a, -self.t / self.a)

    def rigid(self) -> Similarity:
        """Return the pose correction of spec §2: yaw and translation only (scale set to 1)."""
        return Similarity(self.a / abs(self.a), self.t)

    def matrix(self) -> np.ndarray:
        """Return the 2x3 affine matrix of the similarity."""
        a, t = self.a, self.t
        return np.array([[a.real, -a.imag, t.real], [a.imag, a.real, t.imag]])


IDENTITY = Similarity(1.0 + 0j, 0j)


def fit_affine(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Return the least-squares affine (2x3, src -> dst units) of point pairs (N, 2), or None below 4 pairs."""
    if len(src) < 4:
        return None
    design = np.hstack([np.asarray(src, np.float64), np.ones((len(src), 1))])
    solution, _, rank, _ = np.linalg.lstsq(design, np.asarray(dst, np.float64), rcond=None)
    return solution.T if rank == 3 else None


def lsq_similarity(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Return the least-squares similarity dst ~ a src + t of complex point sets (t in their units)."""
    ms, md = src.mean(), dst.mean()
    s, d = src - ms, dst - md
    a = complex(np.vdot(s, d) / max(np.vdot(s, s).real, 1e-12))
    return Similarity(a, complex(md - a * ms))
