"""One Settings object for the API, the workers and the command line (services.settings)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from cli.commands_service import _settings_for
from cli.main import build_parser as cli_parser
from cli.main import main as cli_main
from services.settings import MIN_API_KEY_CHARS, MIN_TOKEN_SECRET_CHARS, Settings, WorkerSettings
from workers.config import WorkerConfig
from workers.main import build_parser as worker_parser
from workers.main import worker_config


@pytest.fixture(autouse=True)
def clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    for name in list(os.environ):
        if name.startswith("VEINMOSAIC_") or name == "REDIS_URL":
            monkeypatch.delenv(name)


def test_worker_timings_come_from_one_json_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    assert Settings().worker_config == WorkerSettings()
    monkeypatch.setenv("VEINMOSAIC_WORKER_CONFIG", json.dumps({"flush_every_s": 0.3, "debug_order": True}))
    cfg = Settings().worker_config
    assert cfg.flush_every_s == 0.3 and cfg.debug_order is True and cfg.lease_ms == WorkerSettings().lease_ms
    monkeypatch.setenv("VEINMOSAIC_WORKER_CONFIG", json.dumps({"method_options": {"track_overlap": 0.8}}))
    assert Settings().worker_config.method_options == {"track_overlap": 0.8}


BAD_WORKER_CONFIGS = [
    {"flush_evry_s": 0.3},
    {"lease_ms": "soon"},
    {"lease_ms": 0},
    {"method": "magic"},
    {"method_options": {"no_such_option": 1}},  # the live method's options: checked as a reprocess request's
    {"method_options": {"track_overlap": 1.5}},
]


@pytest.mark.parametrize("doc", BAD_WORKER_CONFIGS)
def test_a_bad_worker_config_stops_start_up(monkeypatch: pytest.MonkeyPatch, doc: dict) -> None:
    monkeypatch.setenv("VEINMOSAIC_WORKER_CONFIG", json.dumps(doc))
    with pytest.raises(ValidationError):
        Settings()


def test_worker_config_is_the_settings_then_the_command_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("VEINMOSAIC_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VEINMOSAIC_REDIS_PREFIX", "t:")
    monkeypatch.setenv("REDIS_URL", "redis://example:6379/0")
    monkeypatch.setenv("VEINMOSAIC_WORKER_CONFIG", json.dumps({"lease_ms": 4000, "linger_s": 5.0}))
    settings = Settings()
    cfg = worker_config(worker_parser().parse_args([]), settings)
    assert isinstance(cfg, WorkerConfig)
    assert (cfg.data_dir, cfg.prefix, cfg.redis_url) == (tmp_path, "t:", "redis://example:6379/0")
    assert (cfg.lease_ms, cfg.linger_s, cfg.claim_idle_ms) == (4000, 5.0, WorkerSettings().claim_idle_ms)
    args = ["--config-json", json.dumps({"linger_s": 1.0}), "--lease-ms", "900", "--prefix", "x:", "--consumer", "c"]
    cfg = worker_config(worker_parser().parse_args(args), settings)
    assert (cfg.lease_ms, cfg.linger_s, cfg.prefix, cfg.consumer) == (900, 1.0, "x:", "c")
    # --config-json's fields that also have an option of their own hold when the option is left out
    timings = {"lease_ms": 4000, "claim_idle_ms": 1500, "lost_timeout_s": 1.0, "heartbeat_file": "/tmp/beat"}
    cfg = worker_config(worker_parser().parse_args(["--config-json", json.dumps(timings)]), settings)
    assert (cfg.lease_ms, cfg.claim_idle_ms, cfg.lost_timeout_s, cfg.heartbeat_file) == (4000, 1500, 1.0, "/tmp/beat")
    with pytest.raises(ValidationError):
        worker_config(worker_parser().parse_args(["--config-json", '{"bogus": 1}']), settings)


def test_serve_defaults_come_from_the_settings(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    args = cli_parser().parse_args(["serve"])
    assert (args.host, args.port, args.workers, args.data_dir) == (None, None, None, None)
    monkeypatch.setenv("VEINMOSAIC_WORKERS", "3")
    monkeypatch.setenv("VEINMOSAIC_DATA_DIR", str(tmp_path))
    _settings_for(args)
    assert (args.host, args.port, args.workers, args.data_dir) == ("127.0.0.1", 8000, 3, tmp_path)
    args = cli_parser().parse_args(["serve", "--workers", "1", "--port", "9001"])
    _settings_for(args)
    assert (args.port, args.workers) == (9001, 1)


def test_short_api_keys_and_token_secret_are_refused_at_start_up(monkeypatch: pytest.MonkeyPatch) -> None:
    short_key, short_secret = "k" * (MIN_API_KEY_CHARS - 1), "s" * (MIN_TOKEN_SECRET_CHARS - 1)
    monkeypatch.setenv("VEINMOSAIC_API_KEYS", json.dumps({short_key: ["ingest"], "k" * MIN_API_KEY_CHARS: ["view"]}))
    with pytest.raises(ValidationError, match=f"at least {MIN_API_KEY_CHARS}") as refused:
        Settings()
    assert short_key not in str(refused.value) and "scopes ingest" in str(refused.value)  # named, never echoed
    monkeypatch.setenv("VEINMOSAIC_API_KEYS", json.dumps({"k" * MIN_API_KEY_CHARS: ["view"]}))
    monkeypatch.setenv("VEINMOSAIC_TOKEN_SECRET", short_secret)
    with pytest.raises(ValidationError, match=f"at least {MIN_TOKEN_SECRET_CHARS}") as refused:
        Settings()
    assert short_secret not in str(refused.value)
    monkeypatch.setenv("VEINMOSAIC_TOKEN_SECRET", "s" * MIN_TOKEN_SECRET_CHARS)
    assert Settings().token_secret is not None  # the minimum itself is accepted
    monkeypatch.setenv("VEINMOSAIC_PREVIOUS_TOKEN_SECRETS", json.dumps(["p" * MIN_TOKEN_SECRET_CHARS, short_secret]))
    with pytest.raises(ValidationError, match=f"at least {MIN_TOKEN_SECRET_CHARS}") as refused:
        Settings()  # a rotated-out secret is held to the same minimum
    assert short_secret not in str(refused.value)
    monkeypatch.setenv("VEINMOSAIC_PREVIOUS_TOKEN_SECRETS", json.dumps(["p" * MIN_TOKEN_SECRET_CHARS]))
    assert len(Settings().previous_token_secrets) == 1


def test_a_short_key_stops_the_command_line_with_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("VEINMOSAIC_API_KEYS", json.dumps({"short-key": ["ingest"]}))
    assert cli_main(["serve", "--port", "0"]) != 0
    err = capsys.readouterr().err
    assert "at least 24 are required" in err and "short-key" not in err


def test_a_redis_password_never_shows_in_the_settings_repr(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REDIS_URL", "redis://:s3cret-redis-password@redis:6379/0")
    settings = Settings()
    assert settings.redis_url is not None and "s3cret" not in repr(settings) and "s3cret" not in str(settings)
