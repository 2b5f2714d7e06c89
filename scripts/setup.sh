#!/usr/bin/env bash
# Set-up shared by scripts/demo.sh and scripts/test.sh: a virtual environment in .venv with the project
# installed (editable, with test extras), and the viewer's OpenSeadragon from the npm registry. Each step says
# what it does and shows pip's and npm's progress (a first install takes a few minutes); a second run with
# nothing changed skips it all (a stamp of pyproject.toml, constraints.txt, package.json and package-lock.json).
# Python packages are installed at the versions pinned in constraints.txt (refreshed by scripts/lock.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
step() { printf '[setup] %s\n' "$*" >&2; }
if [ ! -x .venv/bin/python ]; then
  "$PY" -c 'import sys; assert sys.version_info >= (3, 11), "veinmosaic needs Python 3.11+"'
  step "creating the virtual environment .venv ($("$PY" --version))"
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(cat pyproject.toml constraints.txt package.json package-lock.json | sha256sum | cut -c1-16)
if [ -f "$stamp" ]; then
  step "dependencies up to date (.venv, node_modules)"
  exit 0
fi
start=$SECONDS
step "1/3 upgrading pip"
.venv/bin/python -m pip install --upgrade --progress-bar on pip 2>&1 | grep -v '^Requirement already satisfied' >&2 || true
step "2/3 installing veinmosaic and its dependencies into .venv (numpy, OpenCV, FastAPI, ...: a few minutes the first time; versions pinned in constraints.txt)"
.venv/bin/python -m pip install --progress-bar on -c constraints.txt -e ".[test]" 2>&1 \
  | grep -E --line-buffered '^(Collecting|Downloading|Installing|Successfully|ERROR|error)|%' >&2 || true
.venv/bin/python -c 'import api, cli, services, workers' || { step "the install failed (see above)"; exit 1; }
if command -v npm >/dev/null 2>&1; then
  step "3/3 installing the viewer's OpenSeadragon (npm ci, pinned in package-lock.json)"
  npm ci --no-audit --no-fund --loglevel=warn >&2
else
  step "3/3 warning: npm not found; the browser viewer needs node_modules/openseadragon (npm ci)"
fi
rm -f .venv/.installed-* && touch "$stamp"
step "done in $((SECONDS - start)) s"
