#!/usr/bin/env bash
# The README's test command: install, lint, check the generated reference pages and build the
# docs strictly (docs/testing.md), run the whole suite once on a clock that reads like a machine
# booted 30 s ago (on the host's clock where no time namespace can be made), then python-can's
# own back-to-back suite against the loopback CAN bus (peer check; its flaky-test policy: a test
# that fails is rerun once, alone, and passes only if the rerun passes, named as "flaky: passed
# on rerun" in the summary line; see scripts/can_peer_suite.py), then the vcan tests on a real
# SocketCAN vcan0 (natively where the host has one, otherwise inside user-mode Linux).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/python scripts/gen_docs.py --check
site_tmp=$(mktemp -d)
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --quiet --site-dir "$site_tmp"
rm -rf "$site_tmp"
bash scripts/fresh_clock_pytest.sh --native-if-unavailable -m "not vcan" --durations=25 "$@"
.venv/bin/python scripts/can_peer_suite.py
.venv/bin/python scripts/vcan_pytest.py
