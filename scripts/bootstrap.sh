#!/usr/bin/env bash
# Create .venv (if missing) and install the project with its test, analysis, sweep and docs
# extras from pyproject.toml.
# Idempotent and quiet when everything is already installed. Needs Python >= 3.11.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  echo "bootstrap: need Python >= 3.11 (set PYTHON=/path/to/python3.11)" >&2
  exit 1
fi
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
stamp=.venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test,analysis,sweep,docs]'
  rm -f .venv/.installed-*
  touch "$stamp"
fi
# Byte-compile the project's own modules (quietly, only what changed): with
# PYTHONDONTWRITEBYTECODE set, as on some CI images, every process of the rig would otherwise
# compile its sources again at each start (about 60 ms of CPU per process).
.venv/bin/python -m compileall -q hal rt_controller plant_emulator vision >/dev/null
# Fill numba's on-disk cache (compiled for this machine's CPU; a no-op when it is current):
# otherwise the first daemon to start compiles every kernel inside its start-up, most of a
# minute on a cold 2-core host, and a rig or test with a wall-clock budget pays for it.
.venv/bin/hil simulate --law rhc --duration 0.1 >/dev/null
