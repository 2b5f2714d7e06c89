"""Place recognition over the placed frames: which kept frames a new frame may overlap, wherever they lie.

A landing frame (the probe set down after a lift) or a frame after lost ones can be anywhere on the map, so it
cannot be searched near a motion prediction only. As ORB-SLAM relocalises a lost camera, each candidate comes
from an index over the kept frames' descriptors, and is then verified geometrically by the caller (a RANSAC
similarity on the frame's full features).

The index is a log-structured set of FLANN k-d-tree shards: new frames wait in a small buffer searched by brute
force; when it fills it becomes a shard, and two shards of the same size are merged into one. A lookup costs one
k-d-tree search per shard (O(log N) shards), whatever the map's size, and building costs O(N log N) in all.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np

DESCRIPTORS_PER_FRAME = 160  # kept per indexed frame, evenly over its features (they are spread over the window)
QUERY_DESCRIPTORS = 200  # a query uses at most this many of the new frame's descriptors
BUFFER_FRAMES = 8  # frames searched by brute force before they become a shard
NEIGHBOURS = 4  # each query descriptor looks at its nearest this many indexed descriptors ...
DISTINCT_RATIO = 0.85  # ... and votes for the frame of each one nearer than this share of the farthest of them
KD_TREES = 4
KD_CHECKS = 32
FLANN_KDTREE = 1


@dataclass(frozen=True)
class _Shard:
    """Descriptors (float32) of some frames, the frame of each row, and their k-d-tree (None: brute force)."""

    descriptors: np.ndarray
    frames: np.ndarray
    tree: cv2.flann.Index | None

    def knn(self, query: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Return (rows (Q, k) int, distances (Q, k) float) of the k nearest descriptors to each query row."""
        k = min(k, len(self.descriptors))
        if self.tree is not None:
            rows, dist2 = self.tree.knnSearch(query, k, params={"checks": KD_CHECKS})
            return rows.astype(np.int64), np.sqrt(np.maximum(dist2, 0.0))
        d2 = (
            np.sum(query**2, axis=1)[:, None]
            - 2.0 * query @ self.descriptors.T
            + np.sum(self.descriptors**2, axis=1)[None, :]
        )
        rows = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < d2.shape[1] else np.argsort(d2, axis=1)
        return rows, np.sqrt(np.maximum(np.take_along_axis(d2, rows, axis=1), 0.0))


def _shard(descriptors: np.ndarray, frames: np.ndarray, tree: bool) -> _Shard:
    index = cv2.flann.Index(descriptors, {"algorithm": FLANN_KDTREE, "trees": KD_TREES}) if tree else None
    return _Shard(descriptors, frames, index)


def index_descriptors(descriptors: np.ndarray, most: int = DESCRIPTORS_PER_FRAME) -> np.ndarray:
    """Return at most `most` rows of a frame's descriptors, evenly over them, as contiguous float32."""
    desc = np.asarray(descriptors, np.float32).reshape(len(descriptors), -1)
    if len(desc) > most:
        desc = desc[np.linspace(0, len(desc) - 1, most).round().astype(np.int64)]
    return np.ascontiguousarray(desc)


@dataclass
class PlaceIndex:
    """Descriptors of the indexed frames, searchable for the frames a new frame's descriptors vote for."""

    _shards: list[_Shard] = field(default_factory=list)
    _buffer: list[tuple[int, np.ndarray]] = field(default_factory=list)
    frames: set[int] = field(default_factory=set)

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: int, descriptors: np.ndarray) -> None:
        """Index a frame's descriptors (a subset, index_descriptors)."""
        desc = index_descriptors(descriptors)
        if len(desc) == 0 or frame in self.frames:
            return
        self.frames.add(frame)
        self._buffer.append((frame, desc))
        if len(self._buffer) >= BUFFER_FRAMES:
            self._seal()

    def _seal(self) -> None:
        """Turn the buffer into a shard; merge the newest shards while two have the same number of rows."""
        desc = np.concatenate([d for _, d in self._buffer])
        frames = np.concatenate([np.full(len(d), f, np.int64) for f, d in self._buffer])
        self._buffer = []
        shard = _shard(desc, frames, tree=True)
        while self._shards and len(self._shards[-1].descriptors) <= len(shard.descriptors):
            last = self._shards.pop()
            desc = np.concatenate([last.descriptors, shard.descriptors])
            frames = np.concatenate([last.frames, shard.frames])
            shard = _shard(desc, frames, tree=True)
        self._shards.append(shard)

    def _all_shards(self) -> list[_Shard]:
        shards = list(self._shards)
        if self._buffer:
            desc = np.concatenate([d for _, d in self._buffer])
            frames = np.concatenate([np.full(len(d), f, np.int64) for f, d in self._buffer])
            shards.append(_shard(desc, frames, tree=False))
        return shards

    def query(self, descriptors: np.ndarray, limit: int, allowed: set[int] | None = None) -> list[tuple[int, int]]:
        """Return up to `limit` (frame, votes) the descriptors vote for, most votes first (ties: newest frame first).

        A query descriptor votes once for each frame among its NEIGHBOURS nearest indexed descriptors (over every
        shard) that is distinctly near (DISTINCT_RATIO of the farthest of them): overlapping indexed frames share a
        vein crossing, so a ratio test against the second nearest alone would reject exactly the true ones.
        allowed: only these frames are counted (None: every indexed frame).
        """
        query = index_descriptors(descriptors, QUERY_DESCRIPTORS)
        shards = self._all_shards()
        if len(query) == 0 or not shards:
            return []
        rows, dists = [], []
        for shard in shards:
            r, d = shard.knn(query, NEIGHBOURS)
            rows.append(shard.frames[r])
            dists.append(d)
        frames = np.concatenate(rows, axis=1)
        dist = np.concatenate(dists, axis=1)
        order = np.argsort(dist, axis=1, kind="stable")[:, :NEIGHBOURS]
        frames = np.take_along_axis(frames, order, axis=1)
        dist = np.take_along_axis(dist, order, axis=1)
        near = dist < DISTINCT_RATIO * dist[:, -1:]
        votes: Counter[int] = Counter()
        for q in range(len(query)):
            for f in set(frames[q][near[q]].tolist()):
                if allowed is None or f in allowed:
                    votes[int(f)] += 1
        ranked = sorted(votes.items(), key=lambda fv: (-fv[1], -fv[0]))
        return ranked[:limit]
