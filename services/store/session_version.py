"""One results version of one session, as every stage and the reconciler see it.

A SessionVersion answers, for (session, version): which frames are stored, the options the version was made
with and the method options and calibration they give, which frames are usable (the one rule: a grayscale 8-
or 16-bit image of the calibration's size), which are handled (prepared or poison), the path row of a rejected
frame, and the version's state (state.json, services.store.version_state). It reads through the raw store
(SessionStore) and the results store (ResultsStore) and keeps nothing but the parsed options.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import cached_property
from typing import Any

import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.inputs.image_header import BadImageError
from services.core.method_options import apply_calibration, parse_options
from services.core.methods import MethodOptions
from services.core.path_rows import PathRow, rejected_row
from services.core.registration.frame_prep import PreparedFrame
from services.store.results_store import LIVE_VERSION, ResultsStore
from services.store.storage import SessionStore, StorageError
from services.store.version_state import VersionState


def method_of(store: SessionStore, sid: str, options: Mapping[str, Any]) -> tuple[MethodOptions, Calibration]:
    """Return the method options and calibration of a version made with `options` (the session's calibration
    with the options' overrides); ValueError naming the field of a bad document, SessionNotFoundError."""
    opts, calib_over = parse_options(dict(options), strict=False)
    return opts, apply_calibration(store.calibration(sid), calib_over)


class SessionVersion:
    """Results version `v` of session `sid`: its frames, options, calibration, usable frames, rows and state."""

    def __init__(self, store: SessionStore, results: ResultsStore, sid: str, v: int) -> None:
        self.store = store
        self.results = results
        self.sid = sid
        self.v = int(v)

    def __repr__(self) -> str:
        return f"SessionVersion({self.sid!r}, {self.v})"

    # ----- the version and its options ------------------------------------------------------------------------
    def exists(self) -> bool:
        """Return True if the version exists (its options.json is written)."""
        return self.results.has_version(self.sid, self.v)

    def ensure(self, options: Mapping[str, Any]) -> bool:
        """Return True if the version was created now with `options` (not when it exists)."""
        if self.exists():  # the common case, without taking the results directory's lock
            return False
        return self.results.ensure_version(self.sid, self.v, dict(options))

    def options_doc(self) -> dict[str, Any]:
        """Return the options.json the version was made with ({} when it does not exist)."""
        return self.results.read_options(self.sid, self.v) or {}

    @cached_property
    def _method(self) -> tuple[MethodOptions, Calibration]:
        return method_of(self.store, self.sid, self.options_doc())

    @property
    def method_options(self) -> MethodOptions:
        """Return the version's method options (from its options.json; read once)."""
        return self._method[0]

    @property
    def calibration(self) -> Calibration:
        """Return the version's calibration: the session's with the options' overrides (read once)."""
        return self._method[1]

    # ----- frames --------------------------------------------------------------------------------------------
    def stored_seqs(self) -> list[int]:
        """Return the seqs of the session's committed frames, ascending."""
        return self.store.frame_seqs(self.sid)

    def frame_t_s(self, seq: int) -> float | None:
        """Return the time (s) of stored frame `seq`, None when it is not stored."""
        rec = self.store.get_frame(self.sid, seq)
        return None if rec is None else rec.t_s

    def load_usable(self, seq: int) -> np.ndarray | None:
        """Return frame `seq` decoded if it is usable (a grayscale 8- or 16-bit image of the calibration's size),
        else None (bad, undecodable, of another size or format, or gone); a storage fault (OSError) is raised."""
        size = self.calibration.image_size
        try:
            img = self.store.load_frame(self.sid, seq, expected_size=size)  # header checked before decoding
        except (StorageError, KeyError, BadImageError):
            return None
        if img.shape != (size[1], size[0]) or img.dtype not in (np.uint8, np.uint16):
            return None
        return img

    def unusable_seqs(self) -> list[int]:
        """Return the seqs of stored frames that are not usable; frames the live run prepared are known to be."""
        return [
            seq
            for seq in self.stored_seqs()
            if not self.results.has_prepared(self.sid, LIVE_VERSION, seq) and self.load_usable(seq) is None
        ]

    def prepared(self, seq: int) -> PreparedFrame | None:
        """Return this version's prepared frame `seq`, None when it is not prepared (yet)."""
        return self.results.read_prepared(self.sid, self.v, seq)

    def prepared_pixels(self, seq: int) -> tuple[np.ndarray, np.ndarray]:
        """Return this version's prepared frame `seq`'s rectified image and window mask (it must be prepared)."""
        return self.results.read_prepared_pixels(self.sid, self.v, seq)

    def is_poison(self, seq: int) -> bool:
        """Return True if frame `seq` was marked poison in this version (it is registered as rejected)."""
        return self.results.is_poison(self.sid, self.v, seq)

    def is_handled(self, seq: int) -> bool:
        """Return True if frame `seq` is prepared or poison in this version."""
        return self.results.has_prepared(self.sid, self.v, seq) or self.is_poison(seq)

    def handled_seqs(self) -> set[int]:
        """Return the seqs of the frames prepared or poison in this version."""
        return self.results.handled_seqs(self.sid, self.v)

    def rejected_row(self, seq: int) -> PathRow:
        """Return the path row of frame `seq` rejected (its stored time, NaN when it is not stored)."""
        t_s = self.frame_t_s(seq)
        return rejected_row(seq, math.nan if t_s is None else t_s)

    # ----- state ---------------------------------------------------------------------------------------------
    def state(self) -> VersionState:
        """Return the version's state (state.json), the initial state before any was written."""
        return self.results.read_state(self.sid, self.v) or VersionState()
