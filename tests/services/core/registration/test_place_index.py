"""The place index: a frame's descriptors find the indexed frames that share them, wherever they are."""

from __future__ import annotations

import math

import numpy as np

from services.core.registration.place_index import BUFFER_FRAMES, PlaceIndex


def _frames(n: int, per_frame: int = 200, seed: int = 3) -> list[np.ndarray]:
    """Return n frames' SIFT-like descriptors (uint8, 128-D), each frame's own."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (per_frame, 128)).astype(np.uint8) for _ in range(n)]


def _seen_again(desc: np.ndarray, seed: int) -> np.ndarray:
    """Return the same points described again: small noise on every descriptor, rows shuffled."""
    rng = np.random.default_rng(seed)
    noisy = np.clip(desc.astype(np.int16) + rng.integers(-6, 7, desc.shape), 0, 255).astype(np.uint8)
    return noisy[rng.permutation(len(noisy))]


def test_a_frame_seen_again_finds_itself_first_in_a_large_index() -> None:
    frames = _frames(150)
    index = PlaceIndex()
    for i, d in enumerate(frames):
        index.add(i, d)
    assert len(index) == 150
    for probe in (0, 7, 77, 149):  # sealed shards of every size and the brute-force buffer
        best, votes = index.query(_seen_again(frames[probe], probe), 3)[0]
        assert best == probe and votes >= 50


def test_two_overlapping_frames_both_get_votes_and_a_stranger_gets_none() -> None:
    a, b, stranger = _frames(3, seed=5)
    b[:100] = a[100:]  # b shares half its points with a (they overlap)
    index = PlaceIndex()
    index.add(10, a)
    index.add(11, b)
    for i, d in enumerate(_frames(30, seed=9)):
        index.add(100 + i, d)
    ranked = dict(index.query(_seen_again(a, 1), 5))
    assert ranked.get(10, 0) >= 50 and ranked.get(11, 0) >= 25  # the shared points vote for both
    assert all(votes < 10 for f, votes in ranked.items() if f >= 100)
    assert not [f for f, v in index.query(_seen_again(stranger, 2), 5) if v >= 10]
    assert dict(index.query(_seen_again(a, 1), 5, allowed={11})).keys() == {11}


def test_the_shards_stay_logarithmic_in_the_frames_indexed() -> None:
    # the lookup searches one k-d tree per shard: their number must grow like log2 of the frames
    index = PlaceIndex()
    for i, d in enumerate(_frames(400, per_frame=20)):
        index.add(i, d)
        sealed = (i + 1) // BUFFER_FRAMES
        assert len(index._shards) <= max(1, math.ceil(math.log2(sealed + 1))) + 1
