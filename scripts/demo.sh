#!/usr/bin/env bash
# The main job: serve (embedded Redis unless REDIS_URL is set), simulate a scan, upload it over HTTP and
# show the result. Extra arguments go to `veinmosaic demo` (e.g. --scenario raster --realtime 1).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/veinmosaic demo "$@"
