#!/usr/bin/env bash
# Set-up shared by scripts/demo.sh and scripts/test.sh: a virtual environment in .venv with the project
# installed (editable, with test extras), and the viewer's OpenSeadragon from the npm registry.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -c 'import sys; assert sys.version_info >= (3, 11), "veinmosaic needs Python 3.11+"'
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(cat pyproject.toml package.json package-lock.json | sha256sum | cut -c1-16)
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -e ".[test]"
  if command -v npm >/dev/null 2>&1; then
    npm ci --no-audit --no-fund --loglevel=error
  else
    echo "warning: npm not found; the browser viewer needs node_modules/openseadragon (npm ci)" >&2
  fi
  rm -f .venv/.installed-* && touch "$stamp"
fi
