"""Set-up never runs silent, and the README says which tests skip without REDIS_URL and why.

scripts/setup.sh is run for real on a copy of the project files, with a fake .venv/bin/python (standing for
pip, printing what pip prints) and a fake npm on PATH: quick, offline, and the real venv is not touched.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FAKE_PYTHON = """#!/bin/sh
# stands for the venv's python: `-m pip install ...` prints what pip prints, other calls succeed quietly
case "$*" in
  *"pip install"*) echo "$*" >> "$(dirname "$0")/pip-calls";
                   echo "Collecting numpy"; echo "  Downloading numpy-2.0.whl (19.5 MB)";
                   echo "     ---------------------------------------- 19.5/19.5 MB 50% eta 0:00:01";
                   echo "Installing collected packages: numpy"; echo "Successfully installed numpy-2.0";;
esac
exit 0
"""
FAKE_NPM = """#!/bin/sh
echo "added 1 package in 1s"
"""


def _executable(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def _run_setup(project: Path, bin_dir: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ.get('PATH', '')}"}
    return subprocess.run(
        ["bash", "scripts/setup.sh"], cwd=project, env=env, capture_output=True, text=True, timeout=60, check=False
    )


def test_setup_shows_each_step_and_pip_progress(tmp_path: Path) -> None:
    project = tmp_path / "project"
    (project / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "setup.sh", project / "scripts" / "setup.sh")
    for name in ("pyproject.toml", "constraints.txt", "package.json", "package-lock.json"):
        shutil.copy(ROOT / name, project / name)
    _executable(project / ".venv" / "bin" / "python", FAKE_PYTHON)
    _executable(tmp_path / "bin" / "npm", FAKE_NPM)

    first = _run_setup(project, tmp_path / "bin")
    assert first.returncode == 0, first.stderr
    err = first.stderr
    # each step is announced before it runs, in order, and the end says how long it took
    steps = [line for line in err.splitlines() if line.startswith("[setup]")]
    assert [s.split()[1] for s in steps[:3]] == ["1/3", "2/3", "3/3"], steps
    assert "a few minutes" in steps[1]  # the long step says it is long
    assert re.fullmatch(r"\[setup\] done in \d+ s", steps[-1]), steps
    # pip's own progress goes through to the terminal (not swallowed), and npm's output too
    assert "Collecting numpy" in err and "Downloading numpy" in err and "50%" in err
    assert "Successfully installed numpy-2.0" in err and "added 1 package" in err

    again = _run_setup(project, tmp_path / "bin")  # nothing changed: says so instead of nothing at all
    assert again.returncode == 0 and "[setup] dependencies up to date" in again.stderr, again.stderr
    assert "Collecting" not in again.stderr


def test_setup_installs_the_pinned_versions_and_reinstalls_when_the_pins_change(tmp_path: Path) -> None:
    project = tmp_path / "project"
    (project / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "setup.sh", project / "scripts" / "setup.sh")
    for name in ("pyproject.toml", "constraints.txt", "package.json", "package-lock.json"):
        shutil.copy(ROOT / name, project / name)
    _executable(project / ".venv" / "bin" / "python", FAKE_PYTHON)
    _executable(tmp_path / "bin" / "npm", FAKE_NPM)
    calls = project / ".venv" / "bin" / "pip-calls"

    assert _run_setup(project, tmp_path / "bin").returncode == 0
    installs = [c for c in calls.read_text().splitlines() if "-e" in c.split()]
    assert len(installs) == 1 and "-c constraints.txt" in installs[0], installs
    with (project / "constraints.txt").open("a") as f:
        f.write("numpy==0.0.1\n")  # a changed pin: the stamp no longer matches, pip runs again
    rerun = _run_setup(project, tmp_path / "bin")
    assert rerun.returncode == 0 and "dependencies up to date" not in rerun.stderr, rerun.stderr
    assert len([c for c in calls.read_text().splitlines() if "-e" in c.split()]) == 2


def test_readme_names_every_test_skipped_without_redis_url_and_why() -> None:
    readme = " ".join((ROOT / "README.md").read_text().split())
    skipping = sorted(
        str(path.relative_to(ROOT))
        for path in (ROOT / "tests").rglob("*.py")
        if re.search(r"pytest\.skip\([^)]*REDIS_URL", path.read_text())
    )
    assert skipping, "no test skips on REDIS_URL any more: update this test and the README"
    for path in skipping:
        assert f"`{path}`" in readme, f"README does not name {path}, which skips without REDIS_URL"
    assert "REDIS_URL not set" in readme  # the reason pytest reports, as the README quotes it
    assert "because a developer machine may have no Redis server" in readme  # and why the suite allows it
