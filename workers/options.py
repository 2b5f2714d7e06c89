"""Kept for imports from before the move: method options are parsed and validated in services.method_options."""

from services.method_options import apply_calibration, parse_options, validate_options, without_values

__all__ = ["apply_calibration", "parse_options", "validate_options", "without_values"]
