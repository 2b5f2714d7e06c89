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

Rotation: with `max_bytes`, a record that would take audit.jsonl past it first renames the file to the next
numbered one (audit-000001.jsonl, audit-000002.jsonl, ... beside it; the directory fsynced) and starts a new
audit.jsonl, whose first record's `prev` is the last hash of the file before: the chain runs on across files,
and `verify` checks them all, oldest first (a missing, reordered or altered file breaks it where it no longer
follows). Rotated files are never deleted by the service: archive them, keeping every file of the chain for
`verify`. A writer whose open file was rotated by another process notices (the path names another inode) and
reopens; a new, empty audit.jsonl continues from the newest rotated file's last hash.

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
import re
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.store.durable import fsync_dir

GENESIS = "0" * 64
CHAIN = "hmac-sha256"  # the `chain` field of a keyed record
_TAIL = 64 * 1024
_ROTATED = re.compile(r"^audit-(\d{6,})\.jsonl$")


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
    files: int = 1  # files of the chain checked (rotated ones, oldest first, then the current one)
    first_bad_file: str | None = None  # the file holding first_bad_line (its name, in the audit folder)

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "ok": self.ok,
            "records": self.records,
            "last_hash": self.last_hash,
            "first_bad_line": self.first_bad_line,
            "reason": self.reason,
            "unkeyed": self.unkeyed,
            "files": self.files,
            "first_bad_file": self.first_bad_file,
        }


class AuditLog:
    """The audit log of one data directory, chained with `key`; thread-safe, and safe across processes on one host."""

    def __init__(self, path: Path, key: bytes, max_bytes: int = 0) -> None:
        if len(key) < 32:
            raise ValueError("the audit key must hold at least 32 bytes")
        self.path = Path(path)
        self._key = key
        self.max_bytes = int(max_bytes)  # rotate before a record would take the file past this (0: never)
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
            self._drop()

    def _drop(self) -> None:
        """Close the open file, after an fsync covering every record written to it (called under self._lock)."""
        if self._fd is None:
            return
        with self._sync_lock:  # an appender waiting for its group commit finds it done, never a closed fd
            try:
                os.fsync(self._fd)
                self._synced = self._written
            finally:
                os.close(self._fd)
                self._fd, self._size = None, -1

    def files(self) -> list[Path]:
        """Return the files of the chain, oldest first: the rotated ones by number, then the current one."""
        rotated = []
        with contextlib.suppress(FileNotFoundError):
            for entry in os.scandir(self.path.parent):
                match = _ROTATED.match(entry.name)
                if match:
                    rotated.append((int(match.group(1)), Path(entry.path)))
        return [p for _, p in sorted(rotated)] + [self.path]

    def _rotated_away(self, fd: int) -> bool:
        """Return True when the path no longer names the open file (another process rotated it)."""
        try:
            named = os.stat(self.path)
        except FileNotFoundError:
            return True
        mine = os.fstat(fd)
        return (named.st_ino, named.st_dev) != (mine.st_ino, mine.st_dev)

    def _rotate(self) -> None:
        """Rename the current file to the next numbered one and fsync the folder (called holding its flock)."""
        last = self.files()[:-1]
        number = int(_ROTATED.match(last[-1].name).group(1)) + 1 if last else 1  # type: ignore[union-attr]
        os.rename(self.path, self.path.parent / f"audit-{number:06d}.jsonl")
        fsync_dir(self.path.parent)

    def _last_rotated_hash(self) -> str:
        """Return the last record's hash of the newest rotated file (GENESIS when there is none)."""
        rotated = self.files()[:-1]
        if not rotated:
            return GENESIS
        fd = os.open(rotated[-1], os.O_RDONLY)
        try:
            size = os.fstat(fd).st_size
            return self._tail(fd, size)[0] if size else GENESIS
        finally:
            os.close(fd)

    def _locked_current(self) -> int:
        """Return the current file's descriptor under its exclusive flock, reopened if another process rotated it."""
        while True:
            fd = self._open()
            fcntl.flock(fd, fcntl.LOCK_EX)
            if not self._rotated_away(fd):
                return fd
            fcntl.flock(fd, fcntl.LOCK_UN)
            self._drop()

    def _tail(self, fd: int, size: int) -> tuple[str, int]:
        """Return (hash of the last complete record, size without a torn last line); an empty file continues the
        newest rotated file's chain."""
        if size == 0:
            return self._last_rotated_hash(), 0
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
            while True:
                fd = self._locked_current()
                try:
                    size = os.fstat(fd).st_size
                    if size != self._size:  # first use, or another process appended (or rotated) meanwhile
                        self._last, good = self._tail(fd, size)
                        if good != size:
                            os.ftruncate(fd, good)  # a torn line from a crash: never acknowledged
                            size = good
                    body = {**record, "prev": self._last, "chain": CHAIN}
                    full = {**body, "hash": record_mac(self._key, body)}
                    line = canonical(full) + b"\n"
                    rotate = bool(self.max_bytes and size and size + len(line) > self.max_bytes)
                    if rotate:  # full: the record goes first in a new file, chained to this file's last
                        self._rotate()
                    else:
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
                if not rotate:
                    break
                self._drop()
        with self._sync_lock:  # group commit: one fsync covers every append made before it started
            if self._synced < mine:
                target = self._written
                os.fsync(fd)
                self._synced = target
        return full

    def _lines_reversed(self) -> Iterator[bytes]:
        """Yield every line of the chain's files, newest first (the current file, then the rotated ones)."""
        for path in reversed(self.files()):
            yield from _file_lines_reversed(path)

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

    def _check(self, raw: bytes, prev: str, keyed_began: bool) -> tuple[str | None, str, bool]:
        """Return (why the line does not follow `prev`, or None; its hash; whether it is an unkeyed record)."""
        try:
            rec = json.loads(raw)
        except ValueError:
            return "not a JSON record", "", False
        if not isinstance(rec, dict) or rec.get("prev") != prev:
            return "prev does not match the previous record's hash", "", False
        legacy = rec.get("chain") != CHAIN
        if legacy and keyed_began:
            return "an unkeyed record after the keyed chain began", "", False
        expected = record_hash(rec) if legacy else record_mac(self._key, rec)
        if not hmac.compare_digest(str(rec.get("hash")), expected):
            return "hash does not match the record (altered, or made without the audit key)", "", False
        return None, expected, legacy

    def verify(self) -> Verification:
        """Return the check of the whole chain from the first record of the oldest file, naming the first line
        (and its file) that does not follow."""
        prev, n, unkeyed = GENESIS, 0, 0
        files = self.files()
        for path in files:
            try:
                fh = open(path, "rb")  # noqa: SIM115 (closed by the with below)
            except FileNotFoundError:
                continue  # no current file yet (or none at all)
            with fh:
                for lineno, raw in enumerate(fh, start=1):
                    reason, digest, legacy = self._check(raw, prev, keyed_began=n > unkeyed)
                    if reason is not None:
                        return Verification(False, n, prev, lineno, reason, unkeyed, len(files), path.name)
                    prev, n, unkeyed = digest, n + 1, unkeyed + legacy
        return Verification(True, n, prev, unkeyed=unkeyed, files=len(files))


def _file_lines_reversed(path: Path) -> Iterator[bytes]:
    """Yield the lines of one file, last first (read backwards in blocks)."""
    try:
        fh = open(path, "rb")  # noqa: SIM115 (closed in finally)
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
