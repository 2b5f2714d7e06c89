"""Results store: versions, lossless prepared frames, write-once setup, path rows, reference parsing, tiles."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.path_rows import PathRow
from services.core.physics.force_model import LoadState
from services.core.registration.features import Features
from services.core.registration.frame_prep import PreparedFrame
from services.store.durable import write_once
from services.store.prepared_file import prepared_from_bytes, prepared_to_bytes
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.storage import SessionStore
from services.store.version_state import VersionState


@pytest.fixture
def stores(tmp_path: Path) -> tuple[ResultsStore, str]:
    store = SessionStore(tmp_path)
    sid = store.create_session("o" * 64, "label", default_calibration()).id
    return ResultsStore(tmp_path), sid


def _prepared(seq: int, desc: np.ndarray) -> PreparedFrame:
    rng = np.random.default_rng(seq)
    n = len(desc)
    return PreparedFrame(
        index=seq,
        seq=seq,
        t_s=1.0 / 3.0 + seq,
        forces_n=rng.normal(size=4),
        load=LoadState(5.123456789, 0.01, -0.02),
        stretch=0.0123,
        image=rng.integers(0, 256, (48, 64), dtype=np.uint8),
        mask=(rng.random((48, 64)) > 0.5).astype(np.uint8) * 255,
        features=Features(rng.normal(size=(n, 2)) * 10, desc, rng.random(n) * 5),
        vein=rng.integers(0, 256, (48, 64), dtype=np.uint8),
        vein_mask=(rng.random((48, 64)) > 0.5).astype(np.uint8) * 255,
        sharpness=123.456,
        focus=0.0171,
    )


def _assert_same(a: PreparedFrame, b: PreparedFrame, focus_kept: bool = True) -> None:
    # lossless: every array and number must come back bit-identical (registration must replay exactly)
    assert (a.index, a.seq, a.t_s, a.load, a.stretch, a.sharpness) == (
        b.index,
        b.seq,
        b.t_s,
        b.load,
        b.stretch,
        b.sharpness,
    )
    for x, y in [
        (a.forces_n, b.forces_n),
        (a.image, b.image),
        (a.mask, b.mask),
        (a.vein, b.vein),
        (a.vein_mask, b.vein_mask),
        (a.features.points, b.features.points),
        (a.features.descriptors, b.features.descriptors),
        (a.features.sizes_px, b.features.sizes_px),
    ]:
        assert x.dtype == y.dtype and np.array_equal(x, y)
    assert a.focus == b.focus or (math.isnan(b.focus) and not focus_kept)
    assert (a.imu_tilt_deg is None) == (b.imu_tilt_deg is None)
    assert a.imu_tilt_deg is None or np.array_equal(a.imu_tilt_deg, b.imu_tilt_deg)


def test_prepared_roundtrip_is_lossless() -> None:
    whole = np.random.default_rng(0).integers(0, 256, (30, 128)).astype(np.float32)  # SIFT-like
    pf = _prepared(3, whole)
    data = prepared_to_bytes(pf)
    _assert_same(pf, prepared_from_bytes(data))
    fractional = whole / 7.0  # not whole numbers: must fall back to float32, still lossless
    _assert_same(_prepared(4, fractional), prepared_from_bytes(prepared_to_bytes(_prepared(4, fractional))))
    assert len(prepared_to_bytes(_prepared(4, fractional))) > len(data)  # uint8 storage is the smaller one
    detected = _prepared(6, whole.astype(np.uint8))  # as features.detect makes them: they come back uint8
    assert prepared_from_bytes(prepared_to_bytes(detected)).features.descriptors.dtype == np.uint8
    _assert_same(detected, prepared_from_bytes(prepared_to_bytes(detected)))
    empty = _prepared(5, np.zeros((0, 128), np.float32))
    _assert_same(empty, prepared_from_bytes(prepared_to_bytes(empty)))
    with_imu = dataclasses.replace(pf, imu_tilt_deg=np.array([1.0 / 3.0, -2.5]))  # an IMU's tilts at the frame
    back = prepared_from_bytes(prepared_to_bytes(with_imu))
    _assert_same(with_imu, back)
    assert back.imu_tilt_deg is not None and prepared_from_bytes(data).imu_tilt_deg is None


def test_a_frame_prepared_without_features_comes_back_without_them() -> None:
    # a method that tracks frames describes only its keyframes, in registration (format 4: features optional)
    pf = dataclasses.replace(_prepared(7, np.zeros((3, 128), np.uint8)), features=None)
    back = prepared_from_bytes(prepared_to_bytes(pf))
    assert back.features is None
    assert np.array_equal(back.vein, pf.vein) and np.array_equal(back.image, pf.image)
    assert len(prepared_to_bytes(pf)) < len(prepared_to_bytes(_prepared(7, np.zeros((300, 128), np.uint8))))


def test_versions_and_current(stores: tuple[ResultsStore, str]) -> None:
    rs, sid = stores
    assert rs.current_version(sid) is None
    assert rs.ensure_version(sid, LIVE_VERSION, {"method": "best"})
    assert not rs.ensure_version(sid, LIVE_VERSION, {"method": "paper"})  # idempotent: first options stay
    assert rs.read_options(sid, 1) == {"method": "best"}
    assert rs.current_version(sid) == 1
    v2 = rs.create_version(sid, {"method": "paper"})
    assert v2 == 2 and rs.current_version(sid) == 2
    v3 = rs.create_version(sid, {"method": "sift-chain"}, make_current=False)
    assert v3 == 3 and rs.current_version(sid) == 2  # reprocess switches only when complete
    rs.set_current(sid, 3)
    assert rs.current_version(sid) == 3 and rs.list_versions(sid) == [1, 2, 3]
    with pytest.raises(ValueError):
        rs.set_current(sid, 9)
    with pytest.raises(ValueError):
        rs.version_dir(sid, 0)
    with pytest.raises(ValueError):
        rs.results_dir("../etc")


def test_shared_mosaic_meta_parses_once_per_written_file(stores: tuple[ResultsStore, str]) -> None:
    rs, sid = stores
    rs.ensure_version(sid, LIVE_VERSION, {"method": "best"})
    assert rs.shared_mosaic_meta(sid, 1) is None  # before the first flush
    rs.write_mosaic_meta(sid, 1, {"version": 1})
    first = rs.shared_mosaic_meta(sid, 1)
    assert first == {"version": 1} and rs.shared_mosaic_meta(sid, 1) is first  # parsed once, shared
    rs.write_mosaic_meta(sid, 1, {"version": 2})  # same size, within the file system's timestamp resolution
    assert rs.shared_mosaic_meta(sid, 1) == {"version": 2}
    assert ResultsStore(rs.data_dir).shared_mosaic_meta(sid, 1) == {"version": 2}  # another process's view


def test_create_version_without_live_keeps_1_free(stores: tuple[ResultsStore, str]) -> None:
    rs, sid = stores
    assert rs.create_version(sid, {}) == 2
    assert rs.ensure_version(sid, LIVE_VERSION, {"method": "best"})
    assert rs.current_version(sid) == 2  # the live run does not take "current" from a reprocess


def test_write_once_and_setup_once(stores: tuple[ResultsStore, str], tmp_path: Path) -> None:
    rs, sid = stores
    target = tmp_path / "once.bin"
    assert write_once(target, b"first")
    assert not write_once(target, b"second")
    assert target.read_bytes() == b"first"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    rs.ensure_version(sid, 1, {})
    assert rs.read_setup(sid, 1) is None
    m1 = np.zeros((4, 5), np.uint8)
    m1[1:3, 1:4] = 255
    got_mask, got_flat = rs.write_setup_once(sid, 1, m1, np.ones((4, 5), np.float32))
    assert np.array_equal(got_mask, m1) and got_flat is not None
    got_mask2, _ = rs.write_setup_once(sid, 1, np.zeros((4, 5), np.uint8), None)  # a later writer loses
    assert np.array_equal(got_mask2, m1)
    rs2 = ResultsStore(rs.data_dir)  # another process reads the first writer's setup from disk
    got_mask3, got_flat3 = rs2.read_setup(sid, 1)
    assert np.array_equal(got_mask3, m1) and np.array_equal(got_flat3, np.ones((4, 5), np.float32))


def test_prepared_first_writer_wins_and_poison(stores: tuple[ResultsStore, str]) -> None:
    rs, sid = stores
    rs.ensure_version(sid, 1, {})
    desc = np.ones((3, 128), np.float32)
    assert rs.read_prepared(sid, 1, 3) is None and not rs.has_prepared(sid, 1, 3)
    assert rs.write_prepared(sid, 1, _prepared(3, desc))
    assert not rs.write_prepared(sid, 1, _prepared(3, desc * 2))
    got = rs.read_prepared(sid, 1, 3)
    assert got is not None and np.array_equal(got.features.descriptors, desc)
    # a live worker re-pastes a frame from its pixels alone: the same arrays, and a clear error when not prepared
    image, mask = rs.read_prepared_pixels(sid, 1, 3)
    assert np.array_equal(image, got.image) and np.array_equal(mask, got.mask) and image.dtype == np.uint8
    with pytest.raises(FileNotFoundError):
        rs.read_prepared_pixels(sid, 1, 4)
    assert not rs.is_poison(sid, 1, 8)
    rs.mark_poison(sid, 1, 8, "bad size")
    assert rs.is_poison(sid, 1, 8)


def test_path_state_meta_report_reference_images_tiles(stores: tuple[ResultsStore, str]) -> None:
    rs, sid = stores
    rs.ensure_version(sid, 1, {})
    nan = math.nan
    rows = [
        PathRow(0, 0.5, 0.0, 0.0, 0.0, 3.0, 0.1, -0.1, 0.01, 0, "ok"),
        PathRow(1, 0.6, nan, nan, nan, nan, nan, nan, nan, 0, "lost"),
    ]
    rs.write_path(sid, 1, rows)
    got = rs.read_path(sid, 1)
    assert got[0]["x_mm"] == 0.0 and got[0]["status"] == "ok"
    assert got[1]["x_mm"] is None and got[1]["t_s"] == 0.6 and got[1]["status"] == "lost"
    assert list(got[0]) == ["seq", "t_s", "x_mm", "y_mm", "yaw_deg", "fz_n", "tilt_x_deg", "tilt_y_deg",
                            "stretch", "inliers", "status", "reason", "stroke", "drag_x_mm", "drag_y_mm"]  # fmt: skip
    assert rs.read_state(sid, 1) is None
    rs.write_state(sid, 1, VersionState(cursor=2, fence=3, lost=[1]))
    assert rs.read_state(sid, 1) == VersionState(cursor=2, fence=3, finished=False, lost=(1,))
    assert rs.read_mosaic_meta(sid, 1) is None
    rs.write_mosaic_meta(sid, 1, {"version": 4})
    assert rs.read_mosaic_meta(sid, 1) == {"version": 4}
    rs.write_report(sid, 1, {"rmse_mm": 1.5})
    assert rs.read_report(sid, 1) == {"rmse_mm": 1.5}
    rs.write_reference(sid, "seq,x_mm,y_mm\n0,0,0\n")
    assert rs.read_reference(sid).startswith("seq,x_mm")
    rs.write_image(sid, 1, "mosaic.png", b"png")
    assert rs.image_path(sid, 1, "mosaic.png").read_bytes() == b"png"
    with pytest.raises(ValueError):
        rs.image_path(sid, 1, "../x.png")
    rs.write_tile(sid, 1, "vein", 12, 3, 4, b"t1")
    rs.write_tile(sid, 1, "force", 12, 3, 4, b"t2", durable=False)
    assert rs.tile_path(sid, 1, "vein", 12, 3, 4).read_bytes() == b"t1"
    assert rs.tile_path(sid, 1, "force", 12, 3, 4).name == "3_4.png"
    rs.delete_tile(sid, 1, "vein", 12, 3, 4)
    rs.delete_tile(sid, 1, "vein", 12, 3, 4)  # idempotent
    assert not rs.tile_path(sid, 1, "vein", 12, 3, 4).exists()
    with pytest.raises(ValueError):
        rs.tile_path(sid, 1, "other", 0, 0, 0)
