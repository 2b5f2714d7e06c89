"""Kept for imports from before the move: the settings live in services.settings (shared by the API and workers)."""

from services.settings import SECRET_BYTES, Settings, get_settings, token_secret_bytes

__all__ = ["SECRET_BYTES", "Settings", "get_settings", "token_secret_bytes"]
