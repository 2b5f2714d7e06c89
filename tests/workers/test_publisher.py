"""The publisher: a durable batch of tiles made durable by one sync of the filesystem, not a fsync per file; the
register stage's frames and CPU counted by kind."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from services.core.mosaic.canvas import PLANES, TILE_PX, SparseCanvas
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.jobs import queue
from services.store import durable, results_store
from services.store.results_store import LIVE_VERSION, ResultsStore
from tests.workers.conftest import Backend
from workers.publisher import Publisher


def test_durable_tiles_are_synced_once_after_the_batch(backend: Backend, monkeypatch: pytest.MonkeyPatch) -> None:
    sid = uuid.uuid4().hex
    (backend.data_dir / "sessions" / sid).mkdir(parents=True)
    results = ResultsStore(backend.data_dir)
    publisher = Publisher(SimpleNamespace(results=results, r=backend.r, prefix=backend.prefix))  # type: ignore[arg-type]
    canvas = SparseCanvas(8.0)
    for key in ((0, 0), (1, 0), (0, -1)):
        canvas.tiles[key] = np.ones((TILE_PX, TILE_PX, PLANES), np.float32)
    pyramid = TilePyramid(DziGeometry.for_mosaic(8.0, 100.0))
    changed = pyramid.update(canvas, set(canvas.tiles))
    fsyncs: list[int] = []
    syncs: list[Path] = []
    on_disk: list[int] = []  # tiles written when the sync ran: it must come after every one
    monkeypatch.setattr(durable.os, "fsync", lambda fd: fsyncs.append(fd))

    def sync(path: Path) -> None:
        syncs.append(path)
        on_disk.append(len(list(results.version_dir(sid, 1).rglob("*.png"))))

    monkeypatch.setattr(results_store, "sync_filesystem", sync)

    revisions: dict[str, dict[str, int]] = {}
    written = publisher.write_tiles(sid, 1, pyramid, changed, 1, revisions, durable=True)
    assert syncs == [results.version_dir(sid, 1)] and not fsyncs  # once, after every tile
    assert on_disk == [2 * len(changed)]  # both layers' tiles
    assert {len(names) for names in written.values()} == {len(changed)}
    for level, col, row in changed:
        for layer in ("vein", "force"):
            assert results.tile_path(sid, 1, layer, level, col, row).read_bytes().startswith(b"\x89PNG")

    publisher.write_tiles(sid, 1, pyramid, changed, 2, revisions, durable=False)  # live tiles: no sync
    assert len(syncs) == 1 and not fsyncs


def test_sync_filesystem_flushes_the_filesystem_of_a_path(tmp_path: Path) -> None:
    durable.replace_bytes(tmp_path / "tile.png", b"png")
    durable.sync_filesystem(tmp_path)  # syncfs(2) here (sync(2) where the C library has none); no error
    with pytest.raises(OSError):
        durable.sync_filesystem(tmp_path / "missing")
    assert os.path.exists(tmp_path / "tile.png")


def test_register_cost_is_counted_by_kind_for_the_live_version_only(backend: Backend) -> None:
    publisher = Publisher(SimpleNamespace(results=None, r=backend.r, prefix=backend.prefix))  # type: ignore[arg-type]
    publisher.count_register_cost(LIVE_VERSION, {"keyframe": 3, "tracked": 5}, {"keyframe": 0.15, "tracked": 0.05})
    publisher.count_register_cost(LIVE_VERSION, {"keyframe": 1}, {"keyframe": 0.05})
    publisher.count_register_cost(LIVE_VERSION + 1, {"keyframe": 7}, {"keyframe": 9.0})  # a reprocess: not counted
    counters = {k.decode(): float(v) for k, v in backend.r.hgetall(queue.metrics_key(backend.prefix)).items()}
    assert counters == pytest.approx(
        {
            "frames_keyframe_total": 4,
            "frames_tracked_total": 5,
            "register_keyframe_cpu_seconds_total": 0.20,
            "register_tracked_cpu_seconds_total": 0.05,
        }
    )
