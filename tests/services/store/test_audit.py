"""The audit log's keyed chain (services.store.audit): records are HMACs with the audit key, so a writer of the
volume without the secret cannot re-chain an edited log; unkeyed records of an older log only as a prefix."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path

import pytest

from services.store.audit import CHAIN, GENESIS, AuditLog, canonical, record_hash, record_mac

KEY = b"audit-store-test-key-0123456789abcdef"


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _write(path: Path, records: list[dict]) -> None:
    path.write_text("".join(canonical(r).decode() + "\n" for r in records))


def _rechain(records: list[dict], start: int, sign: Callable[[dict], str]) -> list[dict]:
    """Return the records with every hash from `start` on recomputed by `sign` (a forger's re-chaining)."""
    out = [dict(r) for r in records]
    for i in range(start, len(out)):
        out[i]["prev"] = out[i - 1]["hash"] if i else GENESIS
        out[i]["hash"] = sign(out[i])
    return out


def _as_unkeyed(record: dict) -> str:
    record.pop("chain", None)
    return record_hash(record)


def test_records_are_chained_with_an_hmac_of_the_audit_key(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.jsonl", KEY)
    for i in range(3):
        log.append({"ts": float(i), "actor": "key:x", "action": "session.read"})
    records = _records(log.path)
    assert all(r["chain"] == CHAIN and r["hash"] == record_mac(KEY, r) != record_hash(r) for r in records)
    result = log.verify()
    assert result.ok and result.records == 3 and result.unkeyed == 0 and result.last_hash == records[-1]["hash"]
    assert not AuditLog(log.path, b"another-key-0123456789abcdef-012345").verify().ok  # another key: not ours


@pytest.mark.parametrize(
    "sign",
    [
        record_hash,  # the unkeyed SHA-256 of the record (what the chain used to be)
        lambda r: record_mac(b"a-guessed-key-0123456789abcdef-0123", r),  # an HMAC with another key
        _as_unkeyed,  # posing as a record of an older, unkeyed log
    ],
)
def test_a_record_recomputed_without_the_key_fails_verification(tmp_path: Path, sign: Callable[[dict], str]) -> None:
    log = AuditLog(tmp_path / "audit.jsonl", KEY)
    for i in range(4):
        log.append({"ts": float(i), "actor": "key:x", "action": "session.read", "session": f"s{i}"})
    records = _records(log.path)
    records[1]["session"] = "s9"  # an edit, then the chain "repaired" from it on without the key
    forged = _rechain(records, 1, sign)
    _write(log.path, forged)
    result = AuditLog(log.path, KEY).verify()
    assert not result.ok and result.first_bad_line == 2 and result.records == 1


def test_an_unkeyed_log_continues_keyed_and_verifies_as_a_prefix(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    old = [{"ts": float(i), "actor": "key:x", "action": "session.read"} for i in range(3)]
    _write(path, _rechain(old, 0, record_hash))  # the log an older version wrote (plain SHA-256, no `chain`)
    log = AuditLog(path, KEY)
    log.append({"ts": 3.0, "actor": "key:x", "action": "session.read"})
    result = log.verify()
    assert result.ok and result.records == 4 and result.unkeyed == 3
    records = _records(path)
    late = {"ts": 4.0, "actor": "key:x", "action": "session.read", "prev": records[-1]["hash"]}
    _write(path, [*records, {**late, "hash": hashlib.sha256(canonical(late)).hexdigest()}])
    bad = AuditLog(path, KEY).verify()
    assert not bad.ok and bad.first_bad_line == 5 and "unkeyed" in (bad.reason or "")


def test_key_actors_are_keyed_ids_of_the_fingerprint(tmp_path: Path) -> None:
    fp = hashlib.sha256(b"ingest-key-a-0123456789abcdef").hexdigest()
    mine, theirs = AuditLog(tmp_path / "a", KEY), AuditLog(tmp_path / "b", b"other-deployment-0123456789abcdef-01")
    assert mine.key_actor(fp).startswith("key:") and len(mine.key_actor(fp)) == 4 + 16
    assert mine.key_actor(fp) == mine.key_actor(fp) != theirs.key_actor(fp)  # stable here, unlinkable elsewhere
    assert mine.key_actor(fp) != f"key:{fp[:16]}"  # not the key's unsalted hash


def test_a_short_audit_key_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="32 bytes"):
        AuditLog(tmp_path / "audit.jsonl", b"short")
