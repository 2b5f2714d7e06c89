"""The hand-written JSON log format keeps only whitelisted fields (why it is not python-json-logger: docs/design.md)."""

from __future__ import annotations

import io
import json
import logging

from services.log_format import LOG_FIELDS, make_log_handler, request_id_var


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
    assert "ValueError: boom" in second["exc"] and set(second) <= {"ts", "level", "logger", "msg", "request_id", "exc"}
    assert {"session", "seq", "route", "status"} <= set(LOG_FIELDS)
