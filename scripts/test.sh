#!/usr/bin/env bash
# The README's test command: install, lint, run the whole suite, run it again on a clock that
# reads like a machine booted 30 s ago, then the vcan tests on a real SocketCAN vcan0 (natively
# where the host has one, otherwise inside user-mode Linux).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/python -m pytest -m "not vcan" "$@"
bash scripts/fresh_clock_pytest.sh -m "not vcan" "$@"
.venv/bin/python scripts/vcan_pytest.py
