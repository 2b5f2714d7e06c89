"""What relocalising a frame costs as the map grows (issue 30: an index lookup, not a match against every frame).

    .venv/bin/python bench/relocalisation.py [--sizes 100,400,1600] [--queries 40] [--scan DIR]

A landing frame, or a frame after lost ones, is searched in the place index (services/core/registration/
place_index.py) over every placed map's indexed frames, then its best few candidates are verified by a RANSAC
similarity (a constant cost: at most atlas.CANDIDATES matches). This bench times the part that depends on the
map's size: adding frames to the index (sealing k-d-tree shards, merging them) and a lookup, at each size, against
a brute-force search of every indexed descriptor (what a match against every frame would cost) in the same run.

The indexed frames carry real descriptors: those of the shared clinical scan's frames (--scan, default
../shared/scans/clinical_veins_24), each reused with small noise as another frame once the scan's own run out.
A lookup queries a held-out frame of the scan; "found" is the share of lookups whose top candidate is one of the
frames the query was taken near (its neighbours by seq), as a check that a faster index still finds the place.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DEFAULT_SCAN = REPO.parent / "shared" / "scans" / "clinical_veins_24"


def scan_descriptors(folder: Path, most: int) -> list[tuple[int, np.ndarray]]:
    """Return (seq, SIFT descriptors) of up to `most` contact frames of a scan, as the pipeline prepares them."""
    from services.core.contact import ContactDetector
    from services.core.methods import method_options
    from services.core.pipeline import frame_forces, prepared_frames, window_setup
    from services.store.scan_folder import read_scan_folder

    scan = read_scan_folder(folder)
    options = method_options("best")
    mask, flat = window_setup(scan, options)
    detector = ContactDetector()
    out = []
    for pf in prepared_frames(scan, frame_forces(scan), mask, flat, options):
        if detector.decide(pf.load.fz_n, pf.focus).contact:
            out.append((pf.seq, pf.features.descriptors))
        if len(out) >= most:
            break
    return out


def build(frames: list[tuple[int, np.ndarray]], size: int, rng: np.random.Generator) -> tuple[object, float]:
    """Return (a PlaceIndex of `size` frames, seconds to build it): the scan's frames, then noisy copies."""
    from services.core.registration.place_index import PlaceIndex

    index = PlaceIndex()
    started = time.perf_counter()
    for k in range(size):
        _, desc = frames[k % len(frames)]
        if k >= len(frames):  # another frame with the same kind of content
            desc = np.clip(desc.astype(np.int16) + rng.integers(-8, 9, desc.shape), 0, 255).astype(np.uint8)
        index.add(k, desc)
    return index, time.perf_counter() - started


def brute_force_ms(index: object, query: np.ndarray) -> float:
    """Return the ms of a nearest-descriptor search of the query over every indexed descriptor (no index)."""
    import cv2

    shards = index._all_shards()  # type: ignore[attr-defined]
    train = np.concatenate([s.descriptors for s in shards])
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    started = time.perf_counter()
    matcher.knnMatch(np.asarray(query, np.float32), train, k=4)
    return 1000 * (time.perf_counter() - started)


def main() -> int:
    """Print the table of index build and lookup cost by map size; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="100,400,1600", help="frames indexed (comma list; first: the baseline)")
    parser.add_argument("--queries", type=int, default=40, help="lookups timed per size")
    parser.add_argument("--scan", type=Path, default=DEFAULT_SCAN, help="a scan folder whose frames' descriptors")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    rng = np.random.default_rng(7)
    print(f"descriptors of {args.scan.name}'s contact frames ...", flush=True)
    frames = scan_descriptors(args.scan, max(sizes))
    held = frames[1::10]  # queries: every tenth frame, searched against the others (and their noisy copies)
    pool = [f for k, f in enumerate(frames) if k % 10 != 1]
    head = (
        f"{'frames indexed':>14} | {'shards':>6} | {'build s':>7} | {'lookup ms p50':>13} | {'x baseline':>10} |"
        f" {'brute force ms':>14} | {'found %':>7}"
    )
    print(head)
    print("-" * len(head))
    base = None
    for size in sizes:
        from services.core.registration.place_index import PlaceIndex

        index, build_s = build(pool, size, rng)
        assert isinstance(index, PlaceIndex)
        times, found = [], 0
        for q in range(args.queries):
            seq, desc = held[q % len(held)]
            started = time.perf_counter()
            ranked = index.query(desc, 3)
            times.append(1000 * (time.perf_counter() - started))
            if ranked:
                top_seq = pool[ranked[0][0] % len(pool)][0]
                found += abs(top_seq - seq) <= 3
        p50 = statistics.median(times)
        base = base or p50
        brute = brute_force_ms(index, held[0][1])
        print(
            f"{size:>14} | {len(index._shards):>6} | {build_s:>7.2f} | {p50:>13.1f} | {p50 / base:>10.2f} |"
            f" {brute:>14.1f} | {100 * found / args.queries:>7.0f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
