"""Format versions: prepared frames and state.json record theirs and are read back, or refused by name."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.npz import npz_bytes
from services.store.file_formats import UnknownFormatError
from services.store.prepared_file import (
    PREPARED_FORMAT,
    prepared_from_bytes,
    prepared_pixels_from_bytes,
    prepared_to_bytes,
)
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from services.store.version_state import STATE_FORMAT, VersionState
from tests.services.store.test_results_store import _assert_same, _prepared


def _with_format(data: bytes, fmt: int | None) -> bytes:
    """Return prepared-frame bytes with their "format" entry set to `fmt` (None: left out, as before formats)."""
    z = np.load(io.BytesIO(data), allow_pickle=False)
    arrays = {name: z[name] for name in z.files if name != "format"}
    if fmt is not None:
        arrays["format"] = np.array([fmt], np.int64)
    return npz_bytes(**arrays)


def test_prepared_frames_carry_their_format() -> None:
    pf = _prepared(7, np.ones((3, 128), np.float32))
    data = prepared_to_bytes(pf)
    assert int(np.load(io.BytesIO(data))["format"][0]) == PREPARED_FORMAT == 4
    _assert_same(pf, prepared_from_bytes(data))
    _assert_same(pf, prepared_from_bytes(_with_format(data, 3)))  # format 3: features always there, the same layout
    _assert_same(pf, prepared_from_bytes(_with_format(data, None)))  # written before formats: format 0, read
    _assert_same(pf, prepared_from_bytes(_with_format(data, 1)))  # format 1: the same layout without an IMU
    older = _with_format(_without(data, "focus"), 2)  # format 2: no focus measure, read as unknown (NaN)
    _assert_same(pf, prepared_from_bytes(older), focus_kept=False)
    with pytest.raises(
        UnknownFormatError, match=r"prepared frame 7: format 5 is unknown .*reads formats 0, 1, 2, 3, 4"
    ):
        prepared_from_bytes(_with_format(data, 5), "prepared frame 7")


def test_a_prepared_frames_pixels_are_read_alone_under_the_same_formats() -> None:
    pf = _prepared(7, np.ones((3, 128), np.float32))
    data = prepared_to_bytes(pf)
    for readable in (data, _with_format(data, None), _with_format(data, 3)):  # this format, before formats, older
        image, mask = prepared_pixels_from_bytes(readable)
        assert image.dtype == mask.dtype == np.uint8
        assert np.array_equal(image, pf.image) and np.array_equal(mask, pf.mask)
    with pytest.raises(UnknownFormatError, match=r"prepared frame 7: format 5 is unknown"):
        prepared_pixels_from_bytes(_with_format(data, 5), "prepared frame 7")
    with pytest.raises(KeyError):  # a damaged file without its image is an error, not an empty frame
        prepared_pixels_from_bytes(_without(data, "image"))


def _without(data: bytes, name: str) -> bytes:
    """Return prepared-frame bytes less one entry."""
    z = np.load(io.BytesIO(data), allow_pickle=False)
    return npz_bytes(**{k: z[k] for k in z.files if k != name})


def test_state_json_carries_its_format() -> None:
    state = VersionState(cursor=5, fence=3, finished=True, lost=[1], rejected=[2, 4])
    doc = state.to_json()
    assert doc == {"format": STATE_FORMAT, "cursor": 5, "fence": 3, "finished": True, "failed": False,
                   "lost": [1], "rejected": [2, 4]}  # fmt: skip
    assert VersionState.from_json(json.loads(json.dumps(doc))) == state
    legacy = {"cursor": 5, "fence": 3, "finished": True, "lost": [1], "rejected": [2, 4]}  # before formats
    assert VersionState.from_json(legacy) == state
    assert VersionState.from_json({"finished": False, "failed": True}) == VersionState(failed=True)
    for bad in (2, "1", None, True):
        with pytest.raises(UnknownFormatError, match=r"state\.json: format .* is unknown"):
            VersionState.from_json({**doc, "format": bad})


def test_the_store_names_the_file_it_cannot_read(tmp_path: Path) -> None:
    store = SessionStore(tmp_path)
    sid = store.create_session("o" * 64, "label", default_calibration()).id
    rs = ResultsStore(tmp_path)
    rs.ensure_version(sid, 1, {})
    rs.write_state(sid, 1, VersionState(cursor=1))
    assert json.loads((rs.version_dir(sid, 1) / "state.json").read_bytes())["format"] == STATE_FORMAT
    (rs.version_dir(sid, 1) / "state.json").write_text(json.dumps({**VersionState().to_json(), "format": 9}))
    with pytest.raises(UnknownFormatError, match=f"state.json of session {sid} version 1: format 9"):
        rs.read_state(sid, 1)
    rs.write_prepared(sid, 1, _prepared(3, np.ones((3, 128), np.float32)))
    path = rs.prepared_path(sid, 1, 3)
    path.write_bytes(_with_format(path.read_bytes(), 5))
    with pytest.raises(UnknownFormatError, match=f"prepared frame 3 of session {sid} version 1: format 5"):
        rs.read_prepared(sid, 1, 3)
