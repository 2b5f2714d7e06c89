"""The publisher: a durable batch of tiles made durable by one sync of the filesystem, not a fsync per file; the
whole images written beside the tiles; the register stage's frames and CPU counted by kind."""

from __future__ import annotations

import io
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


def test_tiles_and_whole_images_are_written_together_as_each_alone(backend: Backend) -> None:
    # a flush writes the whole images on a thread beside the tiles: the same files as one after the other
    results = ResultsStore(backend.data_dir)
    publisher = Publisher(SimpleNamespace(results=results, r=backend.r, prefix=backend.prefix))  # type: ignore[arg-type]
    canvas = SparseCanvas(8.0)
    rng = np.random.default_rng(3)
    for key in ((0, 0), (1, 0), (0, -1)):
        canvas.tiles[key] = rng.uniform(0.1, 1.0, (TILE_PX, TILE_PX, PLANES)).astype(np.float32)
    pyramid = TilePyramid(DziGeometry.for_mosaic(8.0, 100.0))
    changed = pyramid.update(canvas, set(canvas.tiles))
    files: dict[str, dict[str, bytes]] = {}
    for way in ("apart", "together"):
        sid = uuid.uuid4().hex
        (backend.data_dir / "sessions" / sid).mkdir(parents=True)
        if way == "apart":
            tiles = publisher.write_tiles(sid, 1, pyramid, changed, 1, {}, durable=True)
            image = publisher.write_images(sid, 1, canvas.render())
        else:
            tiles, meta, (wall_s, cpu_s) = publisher.write_tiles_and_images(
                sid, 1, pyramid, changed, 1, {}, canvas.render, raw_layers=True, durable=True
            )
            assert meta == image and wall_s > 0 and cpu_s > 0  # the images' own time, on their thread
        assert {len(names) for names in tiles.values()} == {len(changed)}
        root = results.version_dir(sid, 1)
        files[way] = {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert "mosaic.png" in files["together"] and "layers.npz" in files["together"]
    # the same bytes, but layers.npz's arrays: a zip member records its time (2 s steps)
    layers = {way: np.load(io.BytesIO(got.pop("layers.npz"))) for way, got in files.items()}
    assert files["together"] == files["apart"]
    assert layers["together"].files == layers["apart"].files
    for name in layers["apart"].files:
        np.testing.assert_array_equal(layers["together"][name], layers["apart"][name])
    # without a render, tiles alone
    sid = uuid.uuid4().hex
    (backend.data_dir / "sessions" / sid).mkdir(parents=True)
    _, meta, seconds = publisher.write_tiles_and_images(
        sid, 1, pyramid, changed, 1, {}, None, raw_layers=False, durable=False
    )
    assert meta is None and seconds == (0.0, 0.0) and not results.image_path(sid, 1, "mosaic.png").exists()


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
