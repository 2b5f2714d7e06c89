"""The Python dependencies: every imported third-party package is declared, and constraints.txt pins each
declared one at a version its bound in pyproject.toml allows (scripts/lock.sh writes it, scripts/setup.sh uses it)."""

from __future__ import annotations

import ast
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
OWN = {"services", "api", "workers", "cli", "tests", "bench", "__future__"}


def _project() -> dict[str, object]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _requirements() -> list[Requirement]:
    project = _project()
    lines = [*project["dependencies"], *project["optional-dependencies"]["test"]]  # type: ignore[index]
    return [Requirement(line) for line in lines]


def _pins() -> dict[str, str]:
    pins: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: not a name==version pin: {line!r}"
            pins[canonicalize_name(name)] = version.strip()
    return pins


def _imported_top_level(folders: tuple[str, ...]) -> set[str]:
    names: set[str] = set()
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names |= {alias.name.split(".")[0] for alias in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in OWN}


def test_every_package_the_code_imports_is_declared() -> None:
    declared = {canonicalize_name(r.name) for r in _requirements()}
    runtime = {canonicalize_name(Requirement(line).name) for line in _project()["dependencies"]}  # type: ignore[attr-defined]
    dists = packages_distributions()
    for module in sorted(_imported_top_level(("services", "api", "workers", "cli"))):
        owners = {canonicalize_name(d) for d in dists.get(module, [])}
        assert owners & runtime, (
            f"{module} is imported by the package but {owners or 'its distribution'} is not a dependency"
        )
    for module in sorted(_imported_top_level(("tests",))):
        owners = {canonicalize_name(d) for d in dists.get(module, [])}
        assert not owners or owners & declared, f"the tests import {module}: declare {owners} (test extras)"


def test_constraints_pin_every_declared_package_within_its_bounds() -> None:
    pins = _pins()
    for req in _requirements():
        if req.marker is not None and not req.marker.evaluate():
            continue
        name = canonicalize_name(req.name)
        if name == "setuptools":  # pip freeze leaves the packaging tools out; the build back-end needs any >=70.1
            continue
        assert name in pins, f"{req.name} is declared but not pinned in constraints.txt: run scripts/lock.sh"
        assert req.specifier.contains(pins[name], prereleases=True), f"{req.name}=={pins[name]} breaks {req}"


def test_opencv_is_bounded_from_the_first_release_with_the_masked_ecc_to_the_next_major() -> None:
    (opencv,) = [r for r in _requirements() if r.name == "opencv-python-headless"]
    assert not opencv.specifier.contains("4.12.0.88") and opencv.specifier.contains("4.13.0.90")
    assert not opencv.specifier.contains("6.0.0")
