"""The HMAC key of viewer tokens: VEINMOSAIC_TOKEN_SECRET, else data_dir/secret, made once per deployment."""

from __future__ import annotations

import os
import time
from pathlib import Path

from services.settings import Settings
from services.store.durable import write_once

SECRET_BYTES = 32


def token_secret_bytes(settings: Settings) -> bytes:
    """Return the HMAC key for viewer tokens: VEINMOSAIC_TOKEN_SECRET, else data_dir/secret (made once).

    The file is created with durable.write_once (a fsynced temp file hard-linked into place, which fails if
    another process won the race), so every process of one deployment reads the same 32 random bytes.
    """
    if settings.token_secret is not None:
        return settings.token_secret.get_secret_value().encode()
    path = Path(settings.data_dir) / "secret"
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        write_once(path, os.urandom(SECRET_BYTES), mode=0o600)
    for _ in range(50):
        data = path.read_bytes()
        if len(data) >= SECRET_BYTES:
            return data
        time.sleep(0.01)  # pragma: no cover - only a hand-made short file gets here
    raise RuntimeError(f"{path} holds fewer than {SECRET_BYTES} bytes; delete it to make a new one")
