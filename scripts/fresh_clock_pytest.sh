#!/usr/bin/env bash
# Run pytest in a time namespace whose CLOCK_MONOTONIC and CLOCK_BOOTTIME read about 30 s, as on
# a machine that booted half a minute ago (CI machines do). Nothing in the suite may depend on the
# machine's uptime. Needs `unshare -T` (util-linux) and the right to create a time namespace
# (root); where either is missing it says so in one line and exits 0, or, given
# `--native-if-unavailable` as its first argument, runs the same pytest on the host's clock.
set -euo pipefail
cd "$(dirname "$0")/.."
native_fallback=0
if [ "${1:-}" = "--native-if-unavailable" ]; then
  native_fallback=1
  shift
fi
FRESH_UPTIME_S=${FRESH_UPTIME_S:-30}
needs="unshare -T needs root and util-linux >= 2.36"
up=$(cut -d. -f1 /proc/uptime)
offset=$((FRESH_UPTIME_S - up))
if ! command -v unshare >/dev/null 2>&1 \
  || ! unshare -T --fork --monotonic="$offset" --boottime="$offset" true 2>/dev/null; then
  if [ "$native_fallback" = 1 ]; then
    echo "fresh-clock run unavailable ($needs): the suite runs on the host's clock"
    exec .venv/bin/python -m pytest "$@"
  fi
  echo "fresh-clock run skipped: cannot create a time namespace here ($needs)"
  exit 0
fi
echo "fresh-clock run: CLOCK_MONOTONIC set to read ~${FRESH_UPTIME_S} s (host uptime ${up} s)"
exec unshare -T --fork --monotonic="$offset" --boottime="$offset" sh -c '
  .venv/bin/python -c "import time; print(f\"fresh-clock run: monotonic reads {time.monotonic():.1f} s\")"
  exec .venv/bin/python -m pytest "$@"' sh "$@"
