#!/usr/bin/env bash
# The test command: set up, make sure the real parts the tests drive are there (chromium, Orthanc, dciodvfy), lint, test.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Real parts the tests use: Debian's chromium (viewer), orthanc + orthanc-dicomweb (a PACS) and dicom3tools
# (dciodvfy, the reference DICOM validator). Installed here when root; otherwise those tests skip with the reason.
missing=()
[ -x /usr/bin/chromium ] || missing+=(chromium)
[ -x /usr/sbin/Orthanc ] || missing+=(orthanc)
[ -e /usr/share/orthanc/plugins/libOrthancDicomWeb.so ] || missing+=(orthanc-dicomweb)
command -v dciodvfy >/dev/null 2>&1 || missing+=(dicom3tools)
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing Debian's ${missing[*]} for the viewer, PACS and DICOM tests ..."
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "warning: ${missing[*]} missing and cannot be installed here; the tests that need them skip or fail" >&2
  fi
fi
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/lint-imports
.venv/bin/python -m pytest "$@"
