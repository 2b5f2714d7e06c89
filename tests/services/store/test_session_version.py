"""SessionVersion: one results version's frames, options and calibration, usable frames, rejected rows and state."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.registration.outcome import STATUS_REJECTED
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.session_version import SessionVersion, method_of
from services.store.storage import SessionStore
from services.store.version_state import VersionState
from tests.services.store.test_results_store import _prepared


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


@pytest.fixture
def stored(tmp_path: Path) -> tuple[SessionStore, ResultsStore, str]:
    """A session (400 x 320 frames) holding a good 8-bit frame 0, a good 16-bit frame 1, a frame of another size
    (2), a colour frame (3), bytes that are no image (5); no frame 4."""
    store = SessionStore(tmp_path)
    sid = store.create_session("o" * 64, "label", default_calibration()).id
    rng = np.random.default_rng(0)
    store.put_frame(sid, 0, 0.0, _png(rng.integers(0, 255, (320, 400), dtype=np.uint8)), "png")
    store.put_frame(sid, 1, 0.1, _png(rng.integers(0, 4095, (320, 400), dtype=np.uint16)), "png")
    store.put_frame(sid, 2, 0.2, _png(np.full((80, 100), 128, np.uint8)), "png")
    store.put_frame(sid, 3, 0.3, _png(np.zeros((320, 400, 3), np.uint8)), "png")
    store.put_frame(sid, 5, 0.5, b"not an image", "png")
    return store, ResultsStore(tmp_path), sid


def test_frames_options_and_calibration(stored: tuple[SessionStore, ResultsStore, str]) -> None:
    store, results, sid = stored
    sv = SessionVersion(store, results, sid, LIVE_VERSION)
    assert sv.stored_seqs() == [0, 1, 2, 3, 5] and store.count_frames(sid) == 5  # one count of the store's
    assert not sv.exists() and sv.options_doc() == {}
    assert sv.ensure({"method": "paper", "source": "live", "calibration": {"px_per_mm": 10.0}})
    assert sv.exists() and not sv.ensure({"method": "best"})  # the first options stay
    assert sv.method_options.name == "paper" and sv.calibration.px_per_mm == 10.0
    assert sv.calibration.image_size == store.calibration(sid).image_size  # the session's, with the overrides
    assert method_of(store, sid, sv.options_doc()) == (sv.method_options, sv.calibration)
    with pytest.raises(ValueError, match=r"options\.method"):
        method_of(store, sid, {"method": "nonsense"})
    assert sv.frame_t_s(1) == pytest.approx(0.1) and sv.frame_t_s(4) is None


def test_the_usable_frame_rule(stored: tuple[SessionStore, ResultsStore, str]) -> None:
    store, results, sid = stored
    live = SessionVersion(store, results, sid, LIVE_VERSION)
    live.ensure({"method": "best"})
    assert live.load_usable(0).dtype == np.uint8 and live.load_usable(1).dtype == np.uint16
    for seq in (2, 3, 4, 5):  # another size, colour, not stored, undecodable
        assert live.load_usable(seq) is None, seq
    assert live.unusable_seqs() == [2, 3, 5]
    # a reprocess version decodes only the frames the live run did not prepare (those are known to be usable)
    results.write_prepared(sid, LIVE_VERSION, _prepared(2, np.ones((1, 128), np.float32)))
    v = results.create_version(sid, {"method": "best", "source": "reprocess", "job": "j"}, make_current=False)
    assert SessionVersion(store, results, sid, v).unusable_seqs() == [3, 5]


def test_handled_frames_rejected_rows_and_state(stored: tuple[SessionStore, ResultsStore, str]) -> None:
    store, results, sid = stored
    sv = SessionVersion(store, results, sid, LIVE_VERSION)
    sv.ensure({"method": "best"})
    assert sv.handled_seqs() == set() and not sv.is_handled(0) and sv.prepared(0) is None
    results.write_prepared(sid, LIVE_VERSION, _prepared(0, np.ones((1, 128), np.float32)))
    results.mark_poison(sid, LIVE_VERSION, 3, "colour")
    assert sv.handled_seqs() == {0, 3} and sv.is_handled(0) and sv.is_handled(3) and sv.is_poison(3)
    assert sv.prepared(0).seq == 0
    row = sv.rejected_row(3)
    assert (row.seq, row.t_s, row.status) == (3, pytest.approx(0.3), STATUS_REJECTED) and math.isnan(row.x_mm)
    assert math.isnan(sv.rejected_row(4).t_s)  # never stored: no time
    assert sv.state() == VersionState()  # before any state.json
    results.write_state(sid, LIVE_VERSION, VersionState(cursor=4, fence=2, lost=[2], rejected=[3]))
    assert sv.state() == VersionState(cursor=4, fence=2, finished=False, failed=False, lost=(2,), rejected=(3,))
