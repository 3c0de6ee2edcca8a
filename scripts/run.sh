#!/usr/bin/env bash
# The README's main-job command: install, then run the live rig (emulator, vision, controller)
# on the paper scenario with the embedded defaults.
# Extra arguments are passed to the command.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
exec .venv/bin/hil up "$@"
