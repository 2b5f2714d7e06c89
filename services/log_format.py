"""JSON-lines logging shared by the API and the workers: one object per line, request and session ids, and only
whitelisted fields — never labels, calibrations, tokens or raw URLs (no patient data in logs). What a failure is
logged and recorded as (describe, failure_reason, failure_frames) follows the same rule: the project's own
messages, never a library's."""

from __future__ import annotations

import contextvars
import errno
import json
import linecache
import logging
import traceback
from pathlib import Path
from typing import Any, TextIO

request_id_var: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="-")
LOG_FIELDS = (
    "session",
    "seq",
    "bytes",
    "frames",
    "method",
    "route",
    "status",
    "duration_ms",
    "worker",
    "finish_s",  # a session's final refinement and restitch (s), in its "session done" line
    "final_flush_s",  # and its final flush: every tile durably, the whole images (s)
    "parts_s",  # both by part: {refine, calibrate, restitch, flush_path, flush_pyramid, flush_tiles, ...} (s)
    "pasted_again",  # the frames the finish pasted again (moved by a quarter pixel or more)
    "unstitched",  # the placed frames left out of the mosaic: their skin was shown (mosaic.stitch_cover)
)


class RequestIdFilter(logging.Filter):
    """Stamp each record with the current request id (taken when the record is made, not when formatted)."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Add record.request_id; keep every record."""
        if not hasattr(record, "request_id"):
            record.request_id = request_id_var.get()
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg, request_id and the whitelisted extra fields."""

    def format(self, record: logging.LogRecord) -> str:
        """Return the record as a JSON line."""
        doc: dict[str, Any] = {
            "ts": round(record.created, 3),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
            "request_id": getattr(record, "request_id", "-"),
        }
        doc.update({k: getattr(record, k) for k in LOG_FIELDS if hasattr(record, k)})
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)

    def formatException(self, ei: Any) -> str:  # noqa: N802 (logging.Formatter's name)
        """Return the exception's frames and type names (exception_frames), never its message or its chain's."""
        _, value, _ = ei
        return exception_frames(value) if isinstance(value, BaseException) else "(no exception)"


def make_log_handler(stream: TextIO | None = None) -> logging.Handler:
    """Return a handler writing JSON lines with request ids to `stream` (stderr by default)."""
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    handler.addFilter(RequestIdFilter())
    return handler


def configure_json_logging(level: str, logger_name: str = "veinmosaic") -> None:
    """Send `logger_name` logs to stderr as JSON lines at `level` (idempotent)."""
    root = logging.getLogger(logger_name)
    root.setLevel(level.upper())
    if not any(isinstance(h.formatter, JsonFormatter) for h in root.handlers):
        root.addHandler(make_log_handler())
        root.propagate = False


# The project's own packages: a message raised there is written to carry no patient data (tests check the routes
# and stages); a library's message (pydicom, numpy, the standard library) may quote whatever value it choked on.
_OWN_PACKAGES = tuple(str(Path(__file__).resolve().parents[1] / name) for name in ("services", "workers", "api", "cli"))


def describe(exc: BaseException) -> str:
    """Return a short description of a fault for logs: the type and errno name, never paths or contents."""
    if isinstance(exc, OSError) and exc.errno is not None:
        return f"{type(exc).__name__} {errno.errorcode.get(exc.errno, exc.errno)}"
    return type(exc).__name__


def _raised_in_own_code(exc: BaseException) -> bool:
    """Return True if a `raise` statement of the project's own packages raised `exc` (not a call it made: int() or
    a library called from there words its message itself)."""
    tb = exc.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    filename = tb.tb_frame.f_code.co_filename
    if not str(Path(filename).resolve()).startswith(_OWN_PACKAGES):
        return False
    return linecache.getline(filename, tb.tb_lineno).lstrip().startswith("raise")


def failure_reason(exc: BaseException) -> str:
    """Return what a job's failure is recorded and logged as: "Type: message" when the project's own code raised
    it, else the type (and errno) alone, since a library's message may quote a patient's value it choked on."""
    if _raised_in_own_code(exc):
        return f"{type(exc).__name__}: {exc}"
    return describe(exc)


_CAUSE = "The above exception was the direct cause of the following exception:"
_CONTEXT = "During handling of the above exception, another exception occurred:"


def _chain(exc: BaseException) -> list[BaseException]:
    """Return `exc` and the exceptions it was raised from or while handling, newest first (cycles cut)."""
    chain: list[BaseException] = []
    current: BaseException | None = exc
    while current is not None and all(current is not e for e in chain):
        chain.append(current)
        if current.__cause__ is not None:
            current = current.__cause__
        elif current.__context__ is not None and not current.__suppress_context__:
            current = current.__context__
        else:
            current = None
    return chain


def exception_frames(exc: BaseException) -> str:
    """Return a traceback of `exc` and its chained exceptions as frames (file, line, function) and type names only.

    What a log line carries of an exception: never a message (a library's may quote the patient value it choked
    on), nor a chained exception's message, nor source lines; the errno name of an OSError is kept (describe).
    """
    blocks: list[str] = []
    oldest_first = _chain(exc)[::-1]
    for older, newer in zip(oldest_first, [*oldest_first[1:], None], strict=True):
        lines = ["Traceback (most recent call last):"]
        frames = traceback.extract_tb(older.__traceback__)
        lines += [f'  File "{f.filename}", line {f.lineno}, in {f.name}' for f in frames]
        kind = type(older)
        name = kind.__qualname__ if kind.__module__ == "builtins" else f"{kind.__module__}.{kind.__qualname__}"
        lines.append(name + describe(older).removeprefix(kind.__name__))
        blocks.append("\n".join(lines))
        if newer is not None:
            blocks.append(_CAUSE if newer.__cause__ is older else _CONTEXT)
    return "\n\n".join(blocks)


def failure_frames(exc: BaseException) -> str:
    """Return the traceback's frames (file, line, function, source line) without the exception's message."""
    return "".join(traceback.format_tb(exc.__traceback__)).rstrip()
