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


def _canvas_and_pyramid() -> tuple[SparseCanvas, TilePyramid, set[tuple[int, int, int]]]:
    """Return a small canvas of a smooth pattern, its pyramid and the tiles that changed."""
    canvas = SparseCanvas(8.0)
    ramp = np.linspace(0.1, 0.9, TILE_PX, dtype=np.float32)
    for key in ((0, 0), (1, 0), (0, -1)):
        tile = np.zeros((TILE_PX, TILE_PX, PLANES), np.float32)
        tile[..., 0], tile[..., 1], tile[..., 2], tile[..., 3] = ramp[None, :], 1.0, 5.0, 1.0
        canvas.tiles[key] = tile
    pyramid = TilePyramid(DziGeometry.for_mosaic(8.0, 100.0))
    return canvas, pyramid, pyramid.update(canvas, set(canvas.tiles))


def test_tiles_and_images_side_by_side_write_what_one_after_the_other_writes(backend: Backend) -> None:
    """The final flush's tiles and whole images, written on two threads, are byte for byte those written in turn."""
    results = ResultsStore(backend.data_dir)
    publisher = Publisher(SimpleNamespace(results=results, r=backend.r, prefix=backend.prefix))  # type: ignore[arg-type]
    canvas, pyramid, changed = _canvas_and_pyramid()
    sids = [uuid.uuid4().hex for _ in range(2)]
    for sid in sids:
        (backend.data_dir / "sessions" / sid).mkdir(parents=True)
    publisher.write_tiles(sids[0], 1, pyramid, changed, 1, {}, durable=True)
    meta = publisher.write_images(sids[0], 1, canvas.render(), raw_layers=True)
    written, meta_side = publisher.write_tiles_and_images(sids[1], 1, pyramid, changed, 1, {}, canvas, durable=True)
    assert meta_side == meta and {len(names) for names in written.values()} == {len(changed)}
    files = [
        sorted(p.relative_to(results.version_dir(sid, 1)) for p in results.version_dir(sid, 1).rglob("*.*"))
        for sid in sids
    ]
    assert files[0] == files[1] and any(p.name == "layers.npz" for p in files[0]) and len(files[0]) > 2 * len(changed)
    for rel in files[0]:
        assert (results.version_dir(sids[0], 1) / rel).read_bytes() == (
            results.version_dir(sids[1], 1) / rel
        ).read_bytes()


def test_an_error_writing_the_images_is_raised_once_the_tiles_are_written(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    results = ResultsStore(backend.data_dir)
    publisher = Publisher(SimpleNamespace(results=results, r=backend.r, prefix=backend.prefix))  # type: ignore[arg-type]
    canvas, pyramid, changed = _canvas_and_pyramid()
    sid = uuid.uuid4().hex
    (backend.data_dir / "sessions" / sid).mkdir(parents=True)

    def full_disk(*_: object, **__: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(results, "write_mosaic_images", full_disk)
    with pytest.raises(OSError, match="No space"):
        publisher.write_tiles_and_images(sid, 1, pyramid, changed, 1, {}, canvas, durable=True)
    assert len(list(results.version_dir(sid, 1).rglob("*.png"))) == 2 * len(changed)  # the tiles went on
