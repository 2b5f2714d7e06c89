"""The hand-written JSON log format keeps only whitelisted fields (why it is not python-json-logger: docs/design.md)."""

from __future__ import annotations

import dataclasses
import io
import ipaddress
import json
import logging
from collections.abc import Callable

import pytest

from services.core.inputs.calibration import default_calibration
from services.core.inputs.image_header import BadImageError, ImageHeader, check_header
from services.log_format import LOG_FIELDS, failure_frames, failure_reason, make_log_handler, request_id_var


def test_only_whitelisted_extras_reach_the_line() -> None:
    buf = io.StringIO()
    logger = logging.getLogger("veinmosaic.test_log_format")
    logger.propagate = False
    handler = make_log_handler(buf)
    logger.addHandler(handler)
    token = request_id_var.set("req-7")
    try:
        logger.warning("frame refused", extra={"session": "s1", "seq": 3, "label": "Jane Doe", "token": "secret"})
        try:
            raise ValueError("boom")
        except ValueError:
            logger.exception("failed", extra={"calibration": {"E": 1}})
    finally:
        request_id_var.reset(token)
        logger.removeHandler(handler)
    first, second = (json.loads(line) for line in buf.getvalue().splitlines())
    assert set(first) == {"ts", "level", "logger", "msg", "request_id", "session", "seq"}
    assert first["request_id"] == "req-7" and first["session"] == "s1" and first["level"] == "WARNING"
    assert "Jane" not in buf.getvalue() and "secret" not in buf.getvalue() and '"E"' not in buf.getvalue()
    assert "ValueError" in second["exc"] and "boom" not in second["exc"]  # frames and type, never the message
    assert set(second) <= {"ts", "level", "logger", "msg", "request_id", "exc"}
    assert {"session", "seq", "route", "status"} <= set(LOG_FIELDS)


# What a failed job or request is recorded and logged as: the project's own messages, never a library's.
PATIENT = "Doe^Jane"  # a value a library or a builtin might quote back in its message


def _caught(fn: Callable[[], object]) -> BaseException:
    with pytest.raises(Exception) as info:
        fn()
    return info.value


def test_a_message_the_projects_own_raise_wrote_is_kept() -> None:
    header = ImageHeader(format="png", width=80, height=100, mode="L")
    exc = _caught(lambda: check_header(header, 4096, (640, 480)))
    assert isinstance(exc, BadImageError)
    assert failure_reason(exc) == f"BadImageError: {exc}" and "calibration image_size" in failure_reason(exc)


def test_a_librarys_message_is_reduced_to_its_type() -> None:
    exc = _caught(lambda: ipaddress.ip_address(PATIENT))  # raised in the standard library, quoting its argument
    assert PATIENT in str(exc)
    assert failure_reason(exc) == "ValueError"


def test_a_builtin_called_from_own_code_is_reduced_too() -> None:
    calib = dataclasses.replace(default_calibration(), camera_matrix=[[1, 0, PATIENT], [0, 1, 2], [0, 0, 1]])
    exc = _caught(lambda: calib.principal_point)  # float() inside services quotes its argument
    assert PATIENT in str(exc)
    assert failure_reason(exc) == "ValueError"


def test_the_logged_frames_name_where_it_failed_but_not_the_message() -> None:
    exc = _caught(lambda: ipaddress.ip_address(PATIENT))
    frames = failure_frames(exc)
    assert "ipaddress.py" in frames and "test_log_format.py" in frames
    assert PATIENT not in frames.replace("ip_address(PATIENT)", "")  # source lines name variables, not values


def test_a_logged_traceback_carries_frames_and_types_but_no_message_of_any_chained_exception() -> None:
    buf = io.StringIO()
    logger = logging.getLogger("veinmosaic.test_log_format.chain")
    logger.propagate = False
    handler = make_log_handler(buf)
    logger.addHandler(handler)

    def parse() -> None:
        try:
            ipaddress.ip_address(PATIENT)
        except ValueError as exc:
            raise KeyError(f"no such patient {PATIENT}") from exc

    try:
        try:
            parse()
        except KeyError:
            open(f"/nonexistent/{PATIENT}")  # noqa: SIM115 (raises while handling the KeyError)
    except OSError:
        logger.exception("failed")
    finally:
        logger.removeHandler(handler)
    exc = json.loads(buf.getvalue())["exc"]
    assert PATIENT not in buf.getvalue() and "Doe" not in buf.getvalue()
    assert "ipaddress.py" in exc and "in parse" in exc and "test_log_format.py" in exc
    assert exc.index("\nValueError") < exc.index("\nKeyError") < exc.index("\nFileNotFoundError ENOENT")
    assert "direct cause" in exc and "During handling" in exc
