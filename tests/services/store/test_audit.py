"""The audit log's keyed chain (services.store.audit): records are HMACs with the audit key, so a writer of the
volume without the secret cannot re-chain an edited log; unkeyed records of an older log only as a prefix."""

from __future__ import annotations

import hashlib
import itertools
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


# ----- rotation: the chain runs on across files ---------------------------------------------------------------------


def _record(i: int) -> dict:
    return {"ts": float(i), "actor": "key:0123456789abcdef", "action": "frame.upload", "status": 202, "seq": i}


def test_the_log_rotates_at_max_bytes_and_the_chain_continues_across_files(tmp_path: Path) -> None:
    path = tmp_path / "audit" / "audit.jsonl"
    log = AuditLog(path, KEY, max_bytes=1000)
    written = [log.append(_record(i)) for i in range(20)]
    files = log.files()
    names = [p.name for p in files]
    assert len(files) >= 4 and names[-1] == "audit.jsonl", names
    assert names[:-1] == [f"audit-{n:06d}.jsonl" for n in range(1, len(files))]
    chained = [rec for p in files for rec in _records(p)]
    assert chained == written  # every record once, in order, over the files
    for before, after in itertools.pairwise(files):
        assert 0 < before.stat().st_size <= 1000
        assert _records(after)[0]["prev"] == _records(before)[-1]["hash"]  # the first chains to the last before
    result = log.verify()
    assert result.ok and result.records == 20 and result.files == len(files) and result.last_hash == written[-1]["hash"]
    assert [r["seq"] for r in log.query(limit=12)] == list(range(19, 7, -1))  # newest first, across files
    assert [r["seq"] for r in AuditLog(path, KEY).query(action="frame.upload", limit=100)] == list(range(19, -1, -1))
    assert AuditLog(path, KEY).verify().to_dict() == result.to_dict()  # the next process checks the same chain


def test_a_new_writer_continues_the_chain_of_the_rotated_files(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    first, second = AuditLog(path, KEY, max_bytes=700), AuditLog(path, KEY, max_bytes=700)  # two processes
    for i in range(12):
        (first if i % 3 else second).append(_record(i))  # each rotates under the other in turn
    assert len(first.files()) >= 3 and first.verify().ok and first.verify().records == 12
    last = first.files()[-1]
    last.unlink()  # the current file is gone (rotated, not yet written): a new one continues from the rotated
    third = AuditLog(path, KEY, max_bytes=700)
    rec = third.append(_record(99))
    assert rec["prev"] != GENESIS and third.verify().ok


def test_a_missing_or_altered_rotated_file_breaks_the_chain_where_it_no_longer_follows(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path, KEY, max_bytes=700)
    for i in range(12):
        log.append(_record(i))
    files = log.files()
    assert len(files) >= 4
    middle = files[1].read_bytes()
    files[1].unlink()  # a whole file taken out of the chain
    gone = log.verify()
    assert not gone.ok and gone.first_bad_file == files[2].name and gone.first_bad_line == 1
    assert "prev does not match" in (gone.reason or "")
    files[1].write_bytes(middle)
    records = _records(files[1])
    records[0]["status"] = 200  # an edit in a rotated file, re-chained without the key
    _write(files[1], records)
    altered = log.verify()
    assert not altered.ok and altered.first_bad_file == files[1].name and altered.first_bad_line == 1
    assert "hash does not match" in (altered.reason or "")


def test_without_max_bytes_the_log_is_one_file(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.jsonl", KEY)
    for i in range(50):
        log.append(_record(i))
    assert log.files() == [tmp_path / "audit.jsonl"] and log.verify().files == 1
