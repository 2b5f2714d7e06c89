"""Kept for imports from before the move: the JSON log format lives in services.log_format."""

from services.log_format import configure_json_logging, make_log_handler, request_id_var

__all__ = ["configure_json_logging", "make_log_handler", "request_id_var"]
