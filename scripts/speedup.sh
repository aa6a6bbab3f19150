#!/usr/bin/env bash
# docs/cluster.md's speed-up from 1 to 2 workers, in local mode and on a local Ray instance:
# the tiny study with 1,500 agent-transitions per policy, run from scratch four times.
# Usage: scripts/speedup.sh [OUT] (default runs/speedup); MODES="local ray" by default.
# Prints one line per run.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-.venv/bin}
OUT=${1:-runs/speedup}
SETS=(--preset tiny --set policy.steps=1500 -q)
mkdir -p "$OUT"
for mode in ${MODES:-local ray}; do
  for workers in 1 2; do
    dir="$OUT/$mode-$workers"
    rm -rf "$dir"
    extra=()
    [ "$mode" = ray ] && extra=(--ray local)
    "$BIN/latentdrive" reproduce "$dir" "${SETS[@]}" --workers "$workers" "${extra[@]}" > /dev/null
    "$BIN/python" -c "import json; r=json.load(open('$dir/results.json'))['meta']['last_run']; \
print(f'$mode, $workers worker(s): {r[\"wall_s\"]:.0f} s')"
  done
done
