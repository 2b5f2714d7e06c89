"""Append-only, keyed hash-chained audit log: one JSON line per record in data_dir/audit/audit.jsonl.

Every record carries `prev`, the hash of the record before it (64 zeros for the first), `chain`
("hmac-sha256") and `hash`, the HMAC-SHA256 with the audit key (services/store/secrets.py) of its own canonical
JSON without `hash` (sorted keys, no spaces). Editing, deleting, inserting or reordering any record breaks the
chain at that point, which `verify` reports; so does a record whose hash was recomputed without the key (a
writer of the volume who does not hold the secret cannot re-chain an edited log). Truncating the tail is only
visible against a hash kept elsewhere (`verify` returns the last hash: an operator may export it). Records
written before the chain was keyed (no `chain` field, a plain SHA-256) are accepted only as a prefix: `verify`
counts them (`unkeyed`), and an unkeyed record after a keyed one breaks the chain.

Durability: a record is written with O_APPEND under an exclusive flock (so several processes on one host
chain correctly: the writer re-reads the last hash whenever the file changed under it) and fsynced before
`append` returns; concurrent appenders share one fsync (group commit). A write that fails (a full disk) is
cut off again, so the file never holds a partial line; a torn line left by a crash (never acknowledged) is
cut off when the log is next opened.

Why a file on the data volume and not a Redis stream: the audit trail must outlive Redis (which may lose its
last second of AOF, or be wiped and rebuilt from the uploads), and it belongs with the patient data it
describes, under the same backups and access control. Records hold ids, keyed key ids (`key_actor`: an HMAC
of the key's fingerprint with the audit key, so a record cannot be matched against a guessed key without the
secret) and addresses, never labels, calibrations, tokens or keys.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import hmac
import json
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

GENESIS = "0" * 64
CHAIN = "hmac-sha256"  # the `chain` field of a keyed record
_TAIL = 64 * 1024


def canonical(record: dict[str, Any]) -> bytes:
    """Return the canonical JSON bytes of a record (sorted keys, no spaces, finite numbers)."""
    return json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def record_hash(record: dict[str, Any]) -> str:
    """Return the SHA-256 hex of a record's canonical JSON without its `hash` field (an unkeyed, legacy record)."""
    return hashlib.sha256(canonical({k: v for k, v in record.items() if k != "hash"})).hexdigest()


def record_mac(key: bytes, record: dict[str, Any]) -> str:
    """Return the HMAC-SHA256 hex, with the audit key, of a record's canonical JSON without its `hash` field."""
    return hmac.new(key, canonical({k: v for k, v in record.items() if k != "hash"}), hashlib.sha256).hexdigest()


@dataclass(frozen=True)
class Verification:
    """Result of `verify`: ok, records checked, the first bad line (1-based) and why, and the last hash."""

    ok: bool
    records: int
    last_hash: str
    first_bad_line: int | None = None
    reason: str | None = None
    unkeyed: int = 0  # records written before the chain was keyed (a prefix of the log)

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "ok": self.ok,
            "records": self.records,
            "last_hash": self.last_hash,
            "first_bad_line": self.first_bad_line,
            "reason": self.reason,
            "unkeyed": self.unkeyed,
        }


class AuditLog:
    """The audit log of one data directory, chained with `key`; thread-safe, and safe across processes on one host."""

    def __init__(self, path: Path, key: bytes) -> None:
        if len(key) < 32:
            raise ValueError("the audit key must hold at least 32 bytes")
        self.path = Path(path)
        self._key = key
        self._lock = threading.Lock()
        self._sync_lock = threading.Lock()
        self._fd: int | None = None
        self._size = -1  # file size after our last append (-1: unknown, re-read the tail)
        self._last = GENESIS
        self._written = 0
        self._synced = 0

    def _open(self) -> int:
        if self._fd is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o640)
        return self._fd

    def key_actor(self, fingerprint: str) -> str:
        """Return the actor of an API key in records: "key:" + 16 hex of an HMAC of its fingerprint (audit key)."""
        return "key:" + hmac.new(self._key, b"key-id:" + fingerprint.encode(), hashlib.sha256).hexdigest()[:16]

    def close(self) -> None:
        """Close the file (a later append opens it again)."""
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd, self._size = None, -1

    def _tail(self, fd: int, size: int) -> tuple[str, int]:
        """Return (hash of the last complete record, size without a torn last line)."""
        if size == 0:
            return GENESIS, 0
        start = max(0, size - _TAIL)
        data = os.pread(fd, size - start, start)
        end = data.rfind(b"\n") + 1
        while end == 0 and start > 0:  # one line longer than the window: read further back
            start = max(0, start - _TAIL)
            data = os.pread(fd, size - start, start)
            end = data.rfind(b"\n") + 1
        if end == 0:
            return GENESIS, 0  # only a torn first line
        good = start + end
        lines = data[:end].rstrip(b"\n").rsplit(b"\n", 1)
        return str(json.loads(lines[-1])["hash"]), good

    def append(self, record: dict[str, Any]) -> dict[str, Any]:
        """Return `record` (JSON-able, without prev/hash) with prev and hash, appended chained and fsynced."""
        with self._lock:
            fd = self._open()
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                size = os.fstat(fd).st_size
                if size != self._size:  # first use, or another process appended meanwhile
                    self._last, good = self._tail(fd, size)
                    if good != size:
                        os.ftruncate(fd, good)  # a torn line from a crash: never acknowledged
                        size = good
                body = {**record, "prev": self._last, "chain": CHAIN}
                full = {**body, "hash": record_mac(self._key, body)}
                line = canonical(full) + b"\n"
                try:
                    written = os.write(fd, line)
                    if written != len(line):
                        raise OSError(28, "short write to the audit log")
                except BaseException:
                    with contextlib.suppress(OSError):
                        os.ftruncate(fd, size)  # no partial line stays behind
                    self._size = -1
                    raise
                self._size, self._last = size + len(line), full["hash"]
                self._written += 1
                mine = self._written
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)
        with self._sync_lock:  # group commit: one fsync covers every append made before it started
            if self._synced < mine:
                target = self._written
                os.fsync(fd)
                self._synced = target
        return full

    def _lines_reversed(self) -> Iterator[bytes]:
        try:
            fh = open(self.path, "rb")  # noqa: SIM115 (closed in finally)
        except FileNotFoundError:
            return
        try:
            pos = fh.seek(0, os.SEEK_END)
            rest = b""
            while pos > 0:
                step = min(_TAIL, pos)
                pos -= step
                fh.seek(pos)
                chunk = fh.read(step) + rest
                parts = chunk.split(b"\n")
                rest = parts[0]
                for line in reversed(parts[1:]):
                    if line:
                        yield line
            if rest:
                yield rest
        finally:
            fh.close()

    def query(
        self,
        session: str | None = None,
        actor: str | None = None,
        action: str | None = None,
        limit: int = 100,
    ) -> list[dict[str, Any]]:
        """Return up to `limit` records matching every given filter, newest first (reads from the end)."""
        out: list[dict[str, Any]] = []
        for line in self._lines_reversed():
            try:
                rec = json.loads(line)
            except ValueError:
                continue  # a torn last line
            if session is not None and rec.get("session") != session:
                continue
            if actor is not None and rec.get("actor") != actor:
                continue
            if action is not None and rec.get("action") != action:
                continue
            out.append(rec)
            if len(out) >= limit:
                break
        return out

    def verify(self) -> Verification:
        """Return the check of the whole chain from the first record, naming the first line that does not follow."""
        prev, n, unkeyed = GENESIS, 0, 0
        try:
            fh = open(self.path, "rb")  # noqa: SIM115 (closed by the with below)
        except FileNotFoundError:
            return Verification(True, 0, GENESIS)
        with fh:
            for lineno, raw in enumerate(fh, start=1):
                try:
                    rec = json.loads(raw)
                except ValueError:
                    return Verification(False, n, prev, lineno, "not a JSON record", unkeyed)
                if not isinstance(rec, dict) or rec.get("prev") != prev:
                    reason = "prev does not match the previous record's hash"
                    return Verification(False, n, prev, lineno, reason, unkeyed)
                if rec.get("chain") == CHAIN:
                    expected = record_mac(self._key, rec)
                elif n > unkeyed:
                    reason = "an unkeyed record after the keyed chain began"
                    return Verification(False, n, prev, lineno, reason, unkeyed)
                else:
                    expected, unkeyed = record_hash(rec), unkeyed + 1
                if not hmac.compare_digest(str(rec.get("hash")), expected):
                    reason = "hash does not match the record (altered, or made without the audit key)"
                    return Verification(False, n, prev, lineno, reason, unkeyed)
                prev, n = rec["hash"], n + 1
        return Verification(True, n, prev, unkeyed=unkeyed)
