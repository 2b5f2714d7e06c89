"""Build hook: every wheel of veinmosaic carries the viewer's pinned OpenSeadragon (the metadata is pyproject.toml's).

build_py copies OpenSeadragon's build (openseadragon.min.js, its button images and its licence) from
node_modules/openseadragon, the version package.json pins and `npm ci` installs, into the wheel's
api/static/vendor/openseadragon, which the viewer serves. The copy goes to the build folder only: the vendored
files are never in the source tree nor in git. When node_modules has no OpenSeadragon yet the hook runs
`npm ci` itself if npm is on PATH, and otherwise stops the build with what to do: a wheel without the viewer
would answer 503 on /viewer/{id}. An editable install (`pip install -e .`) needs no copy: it serves the
checkout's node_modules. An sdist carries the same files (MANIFEST.in), so a wheel built from it has them too.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
OSD_PACKAGE = ROOT / "node_modules" / "openseadragon"
OSD_BUILD = OSD_PACKAGE / "build" / "openseadragon"
VENDOR = ("api", "static", "vendor", "openseadragon")  # inside the wheel, beside api/static's own files


def pinned_version() -> str:
    """Return the OpenSeadragon version package.json pins."""
    return str(json.loads((ROOT / "package.json").read_text())["dependencies"]["openseadragon"])


def installed_version() -> str | None:
    """Return the OpenSeadragon version in node_modules, or None when it is not installed."""
    manifest = OSD_PACKAGE / "package.json"
    if not (manifest.is_file() and (OSD_BUILD / "openseadragon.min.js").is_file()):
        return None
    return str(json.loads(manifest.read_text())["version"])


def ensure_openseadragon() -> None:
    """Make sure node_modules holds the pinned OpenSeadragon (`npm ci` when npm is there), or stop the build."""
    pinned = pinned_version()
    if installed_version() == pinned:
        return
    npm = shutil.which("npm")
    if npm is not None:
        subprocess.run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=warn"], cwd=ROOT, check=True)
    found = installed_version()
    if found != pinned:
        raise SystemExit(
            f"veinmosaic's viewer needs OpenSeadragon {pinned} in node_modules (found {found or 'none'}): run "
            "`npm ci` at the repository root (package-lock.json pins it), then build again"
        )


def vendor_files() -> list[tuple[Path, Path]]:
    """Return (source, path inside the vendor folder) of every file the wheel carries."""
    files = [(OSD_BUILD / "openseadragon.min.js", Path("openseadragon.min.js"))]
    files += [(p, Path("images") / p.name) for p in sorted((OSD_BUILD / "images").glob("*.png"))]
    files.append((OSD_PACKAGE / "LICENSE.txt", Path("LICENSE.txt")))
    return files


class BuildPyWithViewer(build_py):
    """build_py that also copies the pinned OpenSeadragon into the build's api/static/vendor/openseadragon."""

    def run(self) -> None:
        """Build the Python packages, then add the viewer's vendored OpenSeadragon (not in editable mode)."""
        super().run()
        if getattr(self, "editable_mode", False):
            return
        ensure_openseadragon()
        target = Path(self.build_lib, *VENDOR)
        for source, relative in vendor_files():
            dest = target / relative
            dest.parent.mkdir(parents=True, exist_ok=True)
            self.copy_file(str(source), str(dest))

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        """Return build_py's outputs and the vendored files (so installers record them)."""
        outputs = list(super().get_outputs(include_bytecode))
        if not getattr(self, "editable_mode", False):
            outputs += [str(Path(self.build_lib, *VENDOR, rel)) for _, rel in vendor_files()]
        return outputs


setup(cmdclass={"build_py": BuildPyWithViewer})
