"""A plain `pip install` of a wheel serves a working viewer: the wheel carries the pinned OpenSeadragon.

The wheel is built from a copy of the project's files (offline: --no-build-isolation with .venv's setuptools),
installed into a fresh virtual environment whose only other packages are .venv's (a .pth line, no download),
and the installed app, imported outside the checkout, serves /viewer/{id} and OpenSeadragon with 200. The wheel
carries every top-level package (services, api, workers, cli), and its console script `veinmosaic` runs. A tree
without OpenSeadragon and no npm refuses to build (a wheel without the viewer would answer 503).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from tests.api.api_helpers import calibration_doc

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
PROJECT_FILES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "package.json", "package-lock.json")
OSD = "api/static/vendor/openseadragon"
PACKAGES = ("services", "api", "workers", "cli")

CHECK = """
import json, sys
from pathlib import Path
from fastapi.testclient import TestClient
import api
import cli.main
from api.app import create_app
from services.settings import Settings

keys = {"ingest-key-0123456789abcdef": ["ingest"]}
secret = "wheel-test-secret-0123456789abcdef"
app = create_app(Settings(data_dir=Path("data"), redis_url=None, api_keys=keys, token_secret=secret))
with TestClient(app) as client:
    calibration = json.loads(sys.argv[1])
    key = {"Authorization": "Bearer ingest-key-0123456789abcdef"}
    created = client.post("/v1/sessions", json={"calibration": calibration}, headers=key)
    page = client.get(created.json()["viewer_url"])
    osd = client.get("/static/vendor/openseadragon/openseadragon.min.js")
    image = client.get("/static/vendor/openseadragon/images/home_rest.png")
    print(json.dumps({
        "api": api.__file__, "cli": cli.main.__file__, "created": created.status_code, "page": page.status_code,
        "osd": osd.status_code,
        "osd_is_openseadragon": "OpenSeadragon" in osd.text[:5000], "image": image.status_code,
    }))
"""


def _copy_project(dest: Path, with_node_modules: bool) -> Path:
    """Copy what a build needs (the files git holds, plus node_modules/openseadragon when asked) to `dest`."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in PROJECT_FILES:
        shutil.copy(ROOT / name, dest / name)
    for package in PACKAGES:
        shutil.copytree(ROOT / package, dest / package, ignore=shutil.ignore_patterns("vendor", "__pycache__"))
    if with_node_modules:
        shutil.copytree(ROOT / "node_modules" / "openseadragon", dest / "node_modules" / "openseadragon", ignore=ignore)
    return dest


def _build_wheel(project: Path, out: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "pip", "wheel", str(project), "--no-deps", "--no-build-isolation", "-w", str(out)]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, check=False, env=env)


def test_wheel_carries_openseadragon_and_serves_the_viewer(tmp_path: Path) -> None:
    if not (ROOT / "node_modules" / "openseadragon" / "build" / "openseadragon" / "openseadragon.min.js").is_file():
        pytest.fail("node_modules/openseadragon is missing: run `bash scripts/setup.sh` (npm ci)")
    (tmp_path / "src").mkdir()
    built = _build_wheel(_copy_project(tmp_path / "src", with_node_modules=True), tmp_path / "whl")
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    (wheel,) = (tmp_path / "whl").glob("veinmosaic-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {f"{OSD}/openseadragon.min.js", f"{OSD}/images/home_rest.png", f"{OSD}/LICENSE.txt"} <= names
    assert not any(name.startswith("node_modules/") for name in names)
    assert {f"{package}/__init__.py" for package in PACKAGES} <= names
    assert {"cli/main.py", "cli/launcher.py", "cli/client.py"} <= names  # the command line is packaged

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=60)
    python = venv / "bin" / "python"
    install = [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q", str(wheel)]
    subprocess.run(install, check=True, timeout=120)
    # the dependencies come from .venv (offline); veinmosaic itself only from the wheel: .venv's editable
    # install is a finder that a plain .pth path line does not run
    purelib = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    ).stdout.strip()
    (Path(purelib) / "project_venv_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    assert (venv / "bin" / "veinmosaic").is_file()  # the console script `veinmosaic serve` runs

    run_dir = tmp_path / "elsewhere"  # not the checkout: nothing may come from its node_modules
    run_dir.mkdir()
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    done = subprocess.run(
        [str(python), "-c", CHECK, json.dumps(calibration_doc())],
        cwd=run_dir,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["api"].startswith(str(venv)), result  # the installed package, not the checkout
    assert result["cli"].startswith(str(venv)), result
    assert result["created"] == 201 and result["page"] == 200, result
    assert result["osd"] == 200 and result["osd_is_openseadragon"] and result["image"] == 200, result
    script = [str(venv / "bin" / "veinmosaic"), "--help"]
    usage = subprocess.run(script, cwd=run_dir, env=env, capture_output=True, text=True, timeout=60, check=False)
    assert usage.returncode == 0, usage.stderr[-3000:]  # the console script runs cli.main from the wheel
    assert "serve" in usage.stdout and "upload" in usage.stdout, usage.stdout


def test_build_without_openseadragon_or_npm_says_what_to_do(tmp_path: Path) -> None:
    (tmp_path / "src").mkdir()
    project = _copy_project(tmp_path / "src", with_node_modules=False)
    empty_path = tmp_path / "bin"  # no npm on PATH
    empty_path.mkdir()
    built = _build_wheel(project, tmp_path / "whl", env={"PATH": str(empty_path), "HOME": str(tmp_path)})
    assert built.returncode != 0
    assert "npm ci" in built.stdout + built.stderr
    assert not list(tmp_path.glob("whl/*.whl"))
