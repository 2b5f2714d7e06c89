"""The server's HMAC keys: viewer tokens (VEINMOSAIC_TOKEN_SECRET, else data_dir/secret, made once per
deployment) and the audit log's chain and key ids (VEINMOSAIC_AUDIT_SECRET, else derived from the token secret).

The audit key protects the chain only against someone who can write the data volume but cannot read the
secret: set VEINMOSAIC_TOKEN_SECRET (or VEINMOSAIC_AUDIT_SECRET) in the environment, not in data_dir/secret.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import time
from pathlib import Path

from services.settings import Settings
from services.store.durable import write_once

SECRET_BYTES = 32
AUDIT_KEY_LABEL = b"veinmosaic.audit-key"  # the derivation of the audit key from the token secret (its own use)


def token_secrets(settings: Settings) -> list[bytes]:
    """Return the viewer tokens' HMAC keys, oldest first: the previous secrets (still verified), then the current
    one (token_secret_bytes: signs new tokens)."""
    return [*(s.get_secret_value().encode() for s in settings.previous_token_secrets), token_secret_bytes(settings)]


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


def audit_key_bytes(settings: Settings) -> bytes:
    """Return the audit chain's HMAC key: VEINMOSAIC_AUDIT_SECRET, else derived from the token secret."""
    if settings.audit_secret is not None:
        return settings.audit_secret.get_secret_value().encode()
    return hmac.new(token_secret_bytes(settings), AUDIT_KEY_LABEL, hashlib.sha256).digest()
