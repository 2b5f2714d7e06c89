"""A stored session's filing outputs: the one-page report and its DICOM study, built the same way for every caller.

GET export.dcm and sheet.png/pdf (the API) and the PACS send job (the workers) all come here, so a download and
a send of the same session and results version are the same objects with the same UIDs (export_study's key is
the session id, its study the session's study context). The study context is patient data: callers that must
not show it (a viewer link) pass with_study=False and get the objects without it (and so with their own UIDs).

Rendering the sheet takes about a second, so each rendered output of a finished version is kept on disk
(ResultsStore.write_output) and served again while nothing it was made from has changed: its name holds a digest
of the version's finished files (path, mosaic, layers, options), the reference track and frame list (the sheet's
accuracy), the study context when it is shown, and the software version. A new reference or a rewritten mosaic
makes a new digest, so the output is made again (and the stale one removed); with and without the study are
separate outputs. A DICOM object keeps the export time of its first making.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from importlib import metadata

from services.core.mosaic.canvas import MosaicImage
from services.core.outputs.dicom_export import STUDY_OBJECTS, ExportInfo, export_study
from services.core.outputs.session_report import build_session_report
from services.core.outputs.sheet import SheetIdentity
from services.core.path_rows import path_rows_from_json
from services.store.results_store import ResultsStore
from services.store.storage import SessionStore
from services.store.stored_report import BadReferenceError, reference_for_rows


class NotFinishedError(LookupError):
    """The results version has no finished mosaic (layers.npz): processing is not done."""


def finished_version(rs: ResultsStore, sid: str) -> int | None:
    """Return the newest results version up to the current one with a finished mosaic, or None."""
    current = rs.current_version(sid)
    for v in range(current or 0, 0, -1):
        if rs.image_path(sid, v, "layers.npz").is_file():
            return v
    return None


def finished_mosaic(rs: ResultsStore, sid: str, version: int) -> MosaicImage:
    """Return version's finished mosaic (force in N, coverage); NotFinishedError before it is written."""
    mosaic = rs.read_mosaic_layers(sid, version)
    if mosaic is None:
        raise NotFinishedError("no finished mosaic yet: the export is available when processing is done")
    return mosaic


def inputs_digest(store: SessionStore, rs: ResultsStore, sid: str, version: int, with_study: bool) -> str:
    """Return the digest of everything a rendered output of a finished version is made from (see the module)."""
    h = hashlib.sha256()
    h.update(rs.version_stamp(sid, version).encode())
    h.update(b"\0" + hashlib.sha256((rs.read_reference(sid) or "").encode()).digest())
    h.update(b"\0" + ",".join(str(f.seq) for f in store.list_frames(sid)).encode())
    study = store.study(sid) if with_study else None
    h.update(b"\0" + json.dumps(study, sort_keys=True, default=str).encode())
    h.update(b"\0" + software_version().encode())
    return h.hexdigest()[:32]


def _kept(
    store: SessionStore,
    rs: ResultsStore,
    sid: str,
    version: int,
    what: str,
    with_study: bool,
    make: Callable[[], bytes],
) -> bytes:
    """Return the stored output `what` of a finished version if it was made from the same inputs, else make it."""
    if not rs.image_path(sid, version, "layers.npz").is_file():  # not finished: nothing is kept
        raise NotFinishedError("no finished mosaic yet: the export is available when processing is done")
    family = f"{what}.{'study' if with_study else 'nostudy'}."
    name = family + inputs_digest(store, rs, sid, version, with_study)
    data = rs.read_output(sid, version, name)
    if data is None:
        data = make()
        with contextlib.suppress(OSError):  # a full or failing disk: served all the same, made again next time
            rs.write_output(sid, version, name, data, family)
    return data


def session_sheet(
    store: SessionStore, rs: ResultsStore, sid: str, version: int, fmt: str, with_study: bool = True
) -> bytes:
    """Return the one-page report of a finished results version as PNG or PDF bytes (A4), made once."""
    return _kept(
        store,
        rs,
        sid,
        version,
        f"sheet.{fmt}",
        with_study,
        lambda: render_sheet(store, rs, sid, version, fmt, with_study),
    )


def render_sheet(
    store: SessionStore, rs: ResultsStore, sid: str, version: int, fmt: str, with_study: bool = True
) -> bytes:
    """Return the one-page report of a finished results version as PNG or PDF bytes (A4), rendered now."""
    mosaic = finished_mosaic(rs, sid, version)
    meta = store.get_meta(sid)
    rows = path_rows_from_json(rs.read_path(sid, version) or [])
    reference = None
    text = rs.read_reference(sid)
    if text is not None and rows:
        with contextlib.suppress(BadReferenceError):  # the sheet without accuracy
            reference = reference_for_rows(text, rows, (f.seq for f in store.list_frames(sid)))
    tissue = (rs.read_mosaic_meta(sid, version) or {}).get("tissue")
    extra = {"tissue": tissue} if tissue else None
    identity = SheetIdentity(
        session=sid,  # the key, never the label (free text that may name the patient)
        scan_time=datetime.fromtimestamp(meta.created, UTC),
        results_version=version,
        method=(rs.read_options(sid, version) or {}).get("method") or None,
        study=store.study(sid) if with_study else None,
    )
    try:
        report = build_session_report(rows, reference, mosaic, extra, identity=identity)
    except ValueError:  # the reference matches no registered frame: the sheet without accuracy
        report = build_session_report(rows, None, mosaic, extra, identity=identity)
    return report.images[f"sheet.{fmt}"]


def software_version() -> str:
    """Return the installed veinmosaic package's version ('unknown' when it is not installed)."""
    try:
        return metadata.version("veinmosaic")
    except metadata.PackageNotFoundError:
        return "unknown"


def export_info(store: SessionStore, rs: ResultsStore, sid: str, version: int, with_study: bool = True) -> ExportInfo:
    """Return what identifies a session's DICOM study: the session id as key, its study context, dates, method."""
    meta = store.get_meta(sid)
    return ExportInfo(
        key=sid,
        study=store.study(sid) if with_study else None,
        acquired=datetime.fromtimestamp(meta.created, UTC),
        exported=datetime.now(UTC),
        method=str((rs.read_options(sid, version) or {}).get("method") or ""),
        results_version=version,
        software=software_version(),
    )


def session_objects(
    store: SessionStore,
    rs: ResultsStore,
    sid: str,
    version: int,
    with_study: bool = True,
    only: Sequence[str] | None = None,
) -> dict[str, bytes]:
    """Return {object: DICOM Part-10 bytes} of a finished version: each layer and the report (Encapsulated PDF),
    each made once (the download's and the send's objects are the same bytes)."""
    names = tuple(only) if only is not None else STUDY_OBJECTS

    @functools.cache
    def inputs() -> tuple[MosaicImage, ExportInfo]:
        return finished_mosaic(rs, sid, version), export_info(store, rs, sid, version, with_study)

    def make(name: str) -> bytes:
        mosaic, info = inputs()  # read once for every object made in this call
        pdf = session_sheet(store, rs, sid, version, "pdf", with_study) if name == "report" else None
        return export_study(mosaic, info, pdf, only=(name,))[name]

    return {name: _kept(store, rs, sid, version, f"{name}.dcm", with_study, lambda n=name: make(n)) for name in names}
