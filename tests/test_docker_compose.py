"""docker-compose.yml cannot run here (no Docker engine): check that it parses, that every command it runs
exists in the package, and that every variable it sets is a real setting."""

from __future__ import annotations

import importlib
import importlib.util
import tomllib
from pathlib import Path

import yaml

from cli.main import build_parser
from services.settings import Settings

ROOT = Path(__file__).resolve().parents[1]


def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def test_compose_has_redis_with_aof_api_and_scalable_worker() -> None:
    services = compose()["services"]
    assert set(services) == {"proxy", "redis", "api", "worker"}
    assert services["redis"]["image"].startswith("redis:7")
    assert "--appendonly yes" in " ".join(services["redis"]["command"])
    assert "container_name" not in services["worker"], "a fixed container name would prevent --scale"
    assert "ports" not in services["worker"]
    for name in ("redis", "api", "proxy"):
        assert services[name]["healthcheck"]["test"], f"{name} needs a health check"
    volumes = {v.split(":")[0] for v in services["api"]["volumes"]}
    assert volumes == {v.split(":")[0] for v in services["worker"]["volumes"]}, "api and workers share storage"


def test_every_service_restarts_and_has_a_health_check() -> None:
    services = compose()["services"]
    for name, service in services.items():
        assert service.get("restart") in ("always", "unless-stopped", "on-failure"), f"{name}: no restart policy"
        test = service.get("healthcheck", {}).get("test")
        assert test and test[0] in ("CMD", "CMD-SHELL"), f"{name}: no health check"
    # the worker's health check reads the heartbeat file the worker is told to touch
    worker = services["worker"]
    beat = worker["command"][worker["command"].index("--heartbeat-file") + 1]
    assert any(beat in part for part in worker["healthcheck"]["test"])
    from workers.main import build_parser as worker_parser

    assert worker_parser().parse_args(worker["command"][3:]).heartbeat_file == beat


def test_every_command_exists_in_the_package() -> None:
    services = compose()["services"]
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    subcommands = set(build_parser()._subparsers._group_actions[0].choices)
    for name in ("api", "worker"):
        command = services[name]["command"]
        if command[0] == "veinmosaic":
            assert "veinmosaic" in scripts
            assert command[1] in subcommands, f"{name}: veinmosaic has no subcommand {command[1]!r}"
        elif command[:2] == ["python", "-m"]:
            assert importlib.util.find_spec(command[2]) is not None, f"{name}: no module {command[2]}"
        elif command[0] == "uvicorn":
            assert importlib.util.find_spec("uvicorn") is not None
            module, attr = command[1].split(":")
            assert hasattr(importlib.import_module(module), attr), f"{name}: {command[1]} does not exist"
        else:
            raise AssertionError(f"{name}: unexpected command {command[0]!r}")


def test_every_variable_is_a_real_setting() -> None:
    fields = Settings.model_fields
    env_names = set()
    for name, field in fields.items():
        env_names.add(f"VEINMOSAIC_{name.upper()}")
        alias = field.validation_alias
        if alias is not None:
            env_names.update(str(a) for a in getattr(alias, "choices", [alias]))
    for service in ("api", "worker"):
        env = compose()["services"][service]["environment"]
        for var in env:
            assert var in env_names, f"{service} sets {var}, which no setting reads"


def test_only_the_tls_proxy_is_published_and_serves_https_only() -> None:
    services = compose()["services"]
    assert services["proxy"]["ports"] == ["443:443"]  # nothing on port 80
    assert [name for name, service in services.items() if "ports" in service] == ["proxy"]
    assert compose()["networks"]["backend"]["internal"] is True
    for name in ("redis", "api"):
        assert services[name]["networks"] == ["backend"], f"{name} must be reachable on the backend network alone"
    caddyfile = (ROOT / "deploy" / "Caddyfile").read_text()
    mounted = {v.split(":")[0]: v.split(":")[1] for v in services["proxy"]["volumes"]}
    assert mounted["./deploy/Caddyfile"] == "/etc/caddy/Caddyfile" and mounted["./certs"] == "/certs"
    assert "tls /certs/cert.pem /certs/key.pem" in caddyfile and "disable_redirects" in caddyfile
    assert "Strict-Transport-Security" in caddyfile and "reverse_proxy api:8000" in caddyfile
    assert "--proxy-headers" in services["api"]["command"]  # the client address the proxy forwards is trusted


def test_redis_requires_a_password_the_services_use() -> None:
    services = compose()["services"]
    redis = services["redis"]
    assert "requirepass" in " ".join(redis["command"]) and "REDIS_PASSWORD:?" in redis["environment"]["REDIS_PASSWORD"]
    assert "--requirepass" not in " ".join(redis["command"])  # never on a command line (ps shows those)
    assert "REDISCLI_AUTH" in " ".join(redis["healthcheck"]["test"])
    for name in ("api", "worker"):
        assert services[name]["environment"]["REDIS_URL"].startswith("redis://:${REDIS_PASSWORD:?")


def test_the_image_runs_as_a_non_root_user() -> None:
    lines = [line.split() for line in (ROOT / "Dockerfile").read_text().splitlines() if line.strip()]
    users = [words[1] for words in lines if words[0] == "USER"]
    assert users and users[-1] not in ("root", "0"), "the image must end as a non-root user"
    final_stage = [words[0] for words in lines][max(i for i, words in enumerate(lines) if words[0] == "FROM") :]
    assert final_stage.index("USER") < final_stage.index("CMD")
