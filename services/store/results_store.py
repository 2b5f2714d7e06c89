"""Durable results of a session, per results version, on local disk next to the raw uploads.

Layout under data_dir/sessions/<id>/results/:
    current                     the version the API serves (text, an int; written atomically)
    reference.csv               spec §4 reference track, stored once per session (raw text), used by every version
    <v>/options.json            the options the version was made with ({"method": ..., ...})
    <v>/setup.npz               window mask (uint8 0/255) and flat field (float32) or none
    <v>/prepared/<seq>.npz      a PreparedFrame (written once: the first writer wins, later writers are no-ops;
                                versioned: services.store.prepared_file)
    <v>/poison/<seq>.json       a frame that could not be prepared (dead-lettered): registered as "rejected"
    <v>/path.json               spec §4 path rows (null where a frame was not registered)
    <v>/mosaic.json             spec §4 fields + version, revisions, dzi, extent_mm, frames, status
    <v>/tiles/<layer>/<level>/<col>_<row>.png   Deep Zoom tiles, layer "vein" or "force"
    <v>/state.json              the version's VersionState (services.store.version_state; versioned)
    <v>/{mosaic,force,coverage,paths,errors}.png, <v>/report.json
    <v>/layers.npz              raw force (cN) and coverage planes of the finished mosaic (DICOM export, report)
    <v>/outputs/<name>          rendered outputs kept for later calls (the one-page report, DICOM objects), each
                                named by a digest of what it was made from (services.store.session_export)
Version 1 is the live run; reprocess makes 2, 3, ... Every write is atomic (durable.atomic_write_bytes), so
readers (the API, other workers) see a whole old or a whole new file, never a part.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.core.mosaic.canvas import MosaicImage
from services.core.mosaic.layer_images import layers_from_bytes, mosaic_image_files
from services.core.npz import npz_bytes
from services.core.outputs.documents import LAYERS
from services.core.path_rows import PathRow, path_rows_json
from services.core.registration.frame_prep import PreparedFrame
from services.store.durable import (
    atomic_write_bytes,
    directory_lock,
    fsync_dir,
    replace_bytes,
    sync_filesystem,
    write_once,
)
from services.store.prepared_file import prepared_from_bytes, prepared_pixels_from_bytes, prepared_to_bytes
from services.store.version_state import VersionState

IMAGE_NAMES = ("mosaic.png", "force.png", "coverage.png", "paths.png", "errors.png", "layers.npz")
LIVE_VERSION = 1


_SESSION_ID = re.compile(r"^[0-9a-f]{32}$")
_OUTPUT_NAME = re.compile(r"^[a-z0-9][a-z0-9.-]{0,120}$")


def _json_bytes(doc: Any) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()


def _seqs_in(path: Path) -> set[int]:
    try:
        with os.scandir(path) as it:
            return {int(e.name[:6]) for e in it if not e.name.startswith(".") and e.name[:6].isdigit()}
    except FileNotFoundError:
        return set()


SETUP_CACHE = 8  # decoded setup.npz kept per store (sessions processed at once by one worker)
MOSAIC_DOC_CACHE = 64  # parsed mosaic.json documents kept per store (sessions viewed at once by one API process)


class ResultsStore:
    """Results of sessions under data_dir/sessions/<id>/results (layout in the module docstring)."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        self.root = self.data_dir / "sessions"
        # setup.npz never changes once written: the last few are kept decoded (a worker reads it every frame)
        self._setups: OrderedDict[tuple[str, int], tuple[np.ndarray, np.ndarray | None]] = OrderedDict()
        # mosaic.json bytes and their parse, per file: see shared_mosaic_meta
        self._mosaic_docs: dict[Path, tuple[bytes, dict[str, Any]]] = {}

    # ----- versions -----------------------------------------------------------------------------------------
    def results_dir(self, sid: str) -> Path:
        """Return <session>/results (created if missing); ValueError for a malformed session id."""
        if not isinstance(sid, str) or not _SESSION_ID.match(sid):
            raise ValueError("malformed session id")
        path = self.root / sid / "results"
        if not path.is_dir():
            if not (self.root / sid).is_dir():
                raise FileNotFoundError("no such session")
            path.mkdir(exist_ok=True)
        return path

    def version_dir(self, sid: str, v: int) -> Path:
        """Return the directory of results version v (not created here)."""
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or int(v) < 1:
            raise ValueError(f"version must be a positive integer, got {v!r}")
        return self.results_dir(sid) / str(int(v))

    @contextlib.contextmanager
    def _locked(self, sid: str) -> Iterator[Path]:
        rdir = self.results_dir(sid)
        with directory_lock(rdir):
            yield rdir

    def current_version(self, sid: str) -> int | None:
        """Return the version the API serves, or None before any version exists."""
        try:
            return int((self.results_dir(sid) / "current").read_text().strip())
        except (FileNotFoundError, ValueError):
            return None

    def list_versions(self, sid: str) -> list[int]:
        """Return the existing versions, ascending."""
        return sorted(int(p.name) for p in self.results_dir(sid).iterdir() if p.name.isdigit() and p.is_dir())

    def _make_version(self, rdir: Path, v: int, options: dict[str, Any]) -> None:
        vdir = rdir / str(v)
        for sub in ("prepared", "poison", "tiles"):
            (vdir / sub).mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(vdir / "options.json", _json_bytes(options))
        fsync_dir(rdir)

    def create_version(self, sid: str, options: dict[str, Any], make_current: bool = True) -> int:
        """Return the next free version (2, 3, ...; 1 is the live run's), created now and, by default, made current.

        Reprocessing passes make_current=False and calls set_current when the version is complete, so the
        API keeps serving the previous complete version meanwhile.
        """
        with self._locked(sid) as rdir:
            existing = [int(p.name) for p in rdir.iterdir() if p.name.isdigit()]
            v = max([LIVE_VERSION, *existing]) + 1
            (rdir / str(v)).mkdir()
            self._make_version(rdir, v, options)
            if make_current:
                atomic_write_bytes(rdir / "current", str(v).encode())
            return v

    def has_version(self, sid: str, v: int) -> bool:
        """Return True if version v exists (its options.json is written when it is made)."""
        return (self.version_dir(sid, v) / "options.json").exists()

    def set_current(self, sid: str, v: int) -> None:
        """Make version v the one the API serves."""
        if not self.has_version(sid, v):
            raise ValueError(f"version {v} does not exist")
        with self._locked(sid) as rdir:
            atomic_write_bytes(rdir / "current", str(int(v)).encode())

    def ensure_version(self, sid: str, v: int, options: dict[str, Any]) -> bool:
        """Return True if version v was created now (it was missing; current when no version is current yet)."""
        with self._locked(sid) as rdir:
            vdir = rdir / str(int(v))
            if (vdir / "options.json").exists():
                return False
            vdir.mkdir(exist_ok=True)
            self._make_version(rdir, int(v), options)
            if self.current_version(sid) is None:
                atomic_write_bytes(rdir / "current", str(int(v)).encode())
            return True

    def read_options(self, sid: str, v: int) -> dict[str, Any] | None:
        """Return the options.json of version v, or None."""
        return self._read_json(self.version_dir(sid, v) / "options.json")

    # ----- setup and prepared frames ---------------------------------------------------------------------------
    def write_setup_once(
        self, sid: str, v: int, mask: np.ndarray, flat: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Return the stored setup (the first writer's), writing this one unless one exists, so all agree."""
        write_once(self.version_dir(sid, v) / "setup.npz", self._setup_bytes(mask, flat))
        got = self.read_setup(sid, v)
        assert got is not None
        return got

    @staticmethod
    def _setup_bytes(mask: np.ndarray, flat: np.ndarray | None) -> bytes:
        arrays = {"mask": np.asarray(mask, np.uint8)}
        if flat is not None:
            arrays["flat"] = np.asarray(flat, np.float32)
        return npz_bytes(**arrays)

    def read_setup(self, sid: str, v: int) -> tuple[np.ndarray, np.ndarray | None] | None:
        """Return (mask uint8, flat float32 or None) of version v, or None if not computed yet."""
        cached = self._setups.get((sid, v))
        if cached is not None:
            self._setups.move_to_end((sid, v))
            return cached
        try:
            data = (self.version_dir(sid, v) / "setup.npz").read_bytes()
        except FileNotFoundError:
            return None
        z = np.load(io.BytesIO(data), allow_pickle=False)
        setup = (z["mask"], (z["flat"] if "flat" in z.files else None))
        for array in setup:
            if array is not None:
                array.setflags(write=False)  # shared by every later caller
        self._setups[(sid, v)] = setup
        while len(self._setups) > SETUP_CACHE:
            self._setups.popitem(last=False)
        return setup

    def prepared_path(self, sid: str, v: int, seq: int) -> Path:
        """Return the file of a prepared frame."""
        return self.version_dir(sid, v) / "prepared" / f"{int(seq):06d}.npz"

    def write_prepared(self, sid: str, v: int, pf: PreparedFrame) -> bool:
        """Return True if the prepared frame was written now (not when stored already: the first writer wins)."""
        return write_once(self.prepared_path(sid, v, pf.seq), prepared_to_bytes(pf))

    def has_prepared(self, sid: str, v: int, seq: int) -> bool:
        """Return True if frame seq is prepared."""
        return self.prepared_path(sid, v, seq).exists()

    def read_prepared(self, sid: str, v: int, seq: int) -> PreparedFrame | None:
        """Return the prepared frame seq, or None if it is not prepared (yet)."""
        try:
            data = self.prepared_path(sid, v, seq).read_bytes()
        except FileNotFoundError:
            return None
        return prepared_from_bytes(data, f"prepared frame {int(seq)} of session {sid} version {int(v)}")

    def read_prepared_pixels(self, sid: str, v: int, seq: int) -> tuple[np.ndarray, np.ndarray]:
        """Return a prepared frame's rectified image and window mask (uint8); FileNotFoundError if not prepared."""
        data = self.prepared_path(sid, v, seq).read_bytes()
        return prepared_pixels_from_bytes(data, f"prepared frame {int(seq)} of session {sid} version {int(v)}")

    def handled_seqs(self, sid: str, v: int) -> set[int]:
        """Return the seqs of version v's prepared or poison frames (from the file names only: cheap)."""
        vdir = self.version_dir(sid, v)
        return _seqs_in(vdir / "prepared") | _seqs_in(vdir / "poison")

    def mark_poison(self, sid: str, v: int, seq: int, reason: str = "") -> None:
        """Record that frame seq cannot be prepared (it is registered as rejected)."""
        path = self.version_dir(sid, v) / "poison" / f"{int(seq):06d}.json"
        atomic_write_bytes(path, _json_bytes({"seq": int(seq), "reason": reason[:200]}))

    def is_poison(self, sid: str, v: int, seq: int) -> bool:
        """Return True if frame seq was marked poison."""
        return (self.version_dir(sid, v) / "poison" / f"{int(seq):06d}.json").exists()

    # ----- path, state, mosaic meta, report -------------------------------------------------------------------
    def _read_json(self, path: Path) -> Any | None:
        try:
            return json.loads(path.read_bytes())
        except FileNotFoundError:
            return None

    def write_path(self, sid: str, v: int, rows: Sequence[PathRow]) -> None:
        """Write path.json (spec §4 rows)."""
        atomic_write_bytes(self.version_dir(sid, v) / "path.json", _json_bytes(path_rows_json(rows)))

    def read_path(self, sid: str, v: int) -> list[dict[str, Any]] | None:
        """Return the path rows of version v (dicts with the spec §4 columns), or None before any."""
        return self._read_json(self.version_dir(sid, v) / "path.json")

    def write_state(self, sid: str, v: int, state: VersionState) -> None:
        """Write state.json of version v (services.store.version_state: cursor, fence, finished, failed, ...)."""
        atomic_write_bytes(self.version_dir(sid, v) / "state.json", _json_bytes(state.to_json()))

    def read_state(self, sid: str, v: int) -> VersionState | None:
        """Return the state of version v, None before any; UnknownFormatError for a format this release lacks."""
        doc = self._read_json(self.version_dir(sid, v) / "state.json")
        return None if doc is None else VersionState.from_json(doc, f"state.json of session {sid} version {int(v)}")

    def write_mosaic_meta(self, sid: str, v: int, doc: dict[str, Any]) -> None:
        """Write mosaic.json of version v."""
        atomic_write_bytes(self.version_dir(sid, v) / "mosaic.json", _json_bytes(doc))

    def read_mosaic_meta(self, sid: str, v: int) -> dict[str, Any] | None:
        """Return mosaic.json of version v, or None before the first flush."""
        return self._read_json(self.version_dir(sid, v) / "mosaic.json")

    def shared_mosaic_meta(self, sid: str, v: int) -> dict[str, Any] | None:
        """Return mosaic.json of version v, or None before the first flush: READ-ONLY, one parsed copy shared by
        every caller while the file's bytes stay the same (every tile request of the viewers reads it)."""
        path = self.version_dir(sid, v) / "mosaic.json"
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            return None
        hit = self._mosaic_docs.get(path)
        if hit is not None and hit[0] == raw:  # comparing the bytes costs microseconds; parsing them, milliseconds
            return hit[1]
        doc = json.loads(raw)
        if len(self._mosaic_docs) >= MOSAIC_DOC_CACHE:
            self._mosaic_docs.clear()
        self._mosaic_docs[path] = (raw, doc)
        return doc

    def write_report(self, sid: str, v: int, doc: dict[str, Any]) -> None:
        """Write report.json (accuracy report, spec §4) of version v."""
        atomic_write_bytes(self.version_dir(sid, v) / "report.json", _json_bytes(doc))

    def read_report(self, sid: str, v: int) -> dict[str, Any] | None:
        """Return report.json of version v, or None."""
        return self._read_json(self.version_dir(sid, v) / "report.json")

    def write_reference(self, sid: str, csv_text: str) -> None:
        """Store the session's reference.csv (raw text; one per session, used by every version)."""
        atomic_write_bytes(self.results_dir(sid) / "reference.csv", csv_text.encode())

    def read_reference(self, sid: str) -> str | None:
        """Return the stored reference.csv text, or None."""
        try:
            return (self.results_dir(sid) / "reference.csv").read_text()
        except FileNotFoundError:
            return None

    # ----- rendered outputs ---------------------------------------------------------------------------------------
    def output_path(self, sid: str, v: int, name: str) -> Path:
        """Return the file of a rendered output of version v (a name of lowercase letters, digits, '.', '-')."""
        if not _OUTPUT_NAME.match(name):
            raise ValueError("an output name is lowercase letters, digits, '.' and '-'")
        return self.version_dir(sid, v) / "outputs" / name

    def read_output(self, sid: str, v: int, name: str) -> bytes | None:
        """Return a rendered output of version v, or None when it was never stored."""
        try:
            return self.output_path(sid, v, name).read_bytes()
        except FileNotFoundError:
            return None

    def write_output(self, sid: str, v: int, name: str, data: bytes, family: str) -> None:
        """Store a rendered output of version v, removing the other outputs whose names start with `family`
        (the same output made from older inputs: a reference posted since, another software version)."""
        path = self.output_path(sid, v, name)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, data)
        for old in path.parent.glob(f"{family}*"):
            if old.name != name and _OUTPUT_NAME.match(old.name):
                with contextlib.suppress(FileNotFoundError):
                    old.unlink()

    def version_stamp(self, sid: str, v: int) -> str:
        """Return what identifies the finished files of version v (size and mtime of path, mosaic and layers)."""
        parts = []
        for name in ("path.json", "mosaic.json", "mosaic.png", "layers.npz", "options.json"):
            try:
                st = (self.version_dir(sid, v) / name).stat()
                parts.append(f"{name}:{st.st_size}:{st.st_mtime_ns}")
            except FileNotFoundError:
                parts.append(f"{name}:-")
        return ";".join(parts)

    # ----- images and tiles -------------------------------------------------------------------------------------
    def image_path(self, sid: str, v: int, name: str) -> Path:
        """Return the path of a whole image (mosaic.png, force.png, paths.png, errors.png) of version v."""
        if name not in IMAGE_NAMES:
            raise ValueError(f"image name must be one of {IMAGE_NAMES}")
        return self.version_dir(sid, v) / name

    def write_image(self, sid: str, v: int, name: str, png: bytes) -> None:
        """Write a whole image of version v."""
        atomic_write_bytes(self.image_path(sid, v, name), png)

    def write_mosaic_images(self, sid: str, v: int, mosaic: MosaicImage, raw_layers: bool = True) -> None:
        """Write mosaic.png, force.png, coverage.png and (raw_layers) layers.npz of a rendered mosaic."""
        for name, data in mosaic_image_files(mosaic, raw_layers).items():
            self.write_image(sid, v, name, data)

    def read_mosaic_layers(self, sid: str, v: int) -> MosaicImage | None:
        """Return the finished mosaic of version v with force in N and coverage, or None when not written."""
        try:
            raw = self.image_path(sid, v, "layers.npz").read_bytes()
            png = self.image_path(sid, v, "mosaic.png").read_bytes()
        except FileNotFoundError:
            return None
        vein = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
        return layers_from_bytes(raw, vein)

    def tile_path(self, sid: str, v: int, layer: str, level: int, col: int, row: int) -> Path:
        """Return the file of a Deep Zoom tile (it exists only where the tile has data)."""
        if layer not in LAYERS:
            raise ValueError(f"layer must be one of {LAYERS}")
        return self.version_dir(sid, v) / "tiles" / layer / str(int(level)) / f"{int(col)}_{int(row)}.png"

    def write_tile(
        self, sid: str, v: int, layer: str, level: int, col: int, row: int, png: bytes, durable: bool = True
    ) -> None:
        """Write a Deep Zoom tile atomically; durable=False skips the fsyncs (live tiles are rewritten often
        and can be re-rendered; the final flush of a version writes every tile durably)."""
        path = self.tile_path(sid, v, layer, level, col, row)
        path.parent.mkdir(parents=True, exist_ok=True)
        if durable:
            atomic_write_bytes(path, png)
        else:
            replace_bytes(path, png)

    def sync(self, sid: str, v: int) -> None:
        """Make every file of version v written so far durable (tiles written with durable=False): one sync of the
        filesystem, which costs less than a fsync per tile (durable.sync_filesystem)."""
        sync_filesystem(self.version_dir(sid, v))

    def delete_tile(self, sid: str, v: int, layer: str, level: int, col: int, row: int) -> None:
        """Remove a tile that no longer has data (the API then serves a blank tile)."""
        with contextlib.suppress(FileNotFoundError):
            self.tile_path(sid, v, layer, level, col, row).unlink()
