#!/usr/bin/env bash
# Refresh constraints.txt, the pinned versions of every Python package veinmosaic installs (its dependencies,
# the test extras and theirs), from a working install: run it in a checkout whose .venv passes the tests after
# changing a bound in pyproject.toml or upgrading a package on purpose (`.venv/bin/python -m pip install -U X`),
# then commit constraints.txt. scripts/setup.sh (and so CI) installs with `-c constraints.txt`.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
{
  echo "# Pinned versions of veinmosaic's Python dependencies (pip constraints): regenerate with scripts/lock.sh,"
  echo "# never by hand. Used by scripts/setup.sh: pip install -c constraints.txt -e .[test]"
  "$PY" -m pip freeze --exclude-editable --local | LC_ALL=C sort -f
} > constraints.txt.new
mv constraints.txt.new constraints.txt
printf '[lock] constraints.txt: %s packages pinned\n' "$(grep -cv '^#' constraints.txt)" >&2
