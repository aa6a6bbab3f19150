#!/usr/bin/env bash
# The "Does it learn?" results of docs/learning.md: a BNN on fast-backend data, then raw and latent
# policies on intersection and merge, each evaluated on 200 held-out episodes per scenario
# beside the reference policies, with the paired comparison. Rerunning resumes.
# Usage: scripts/learning.sh [OUT] (default runs/learning); STEPS=40000 by default.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-.venv/bin}
OUT=${1:-runs/learning}
STEPS=${STEPS:-40000}
EPISODES=${EPISODES:-200}
COMMON=(--steps "$STEPS" --set segment=5000 --set eval_episodes=50 --set dqn.train_every=2 -q)

"$BIN/latentdrive" collect "$OUT/data" --episodes 120 --set backend=fast -q
if [ ! -f "$OUT/bnn64/checkpoint.safetensors" ]; then
  # The BNN settings the documented results were made with (L2 loss, the paper's model),
  # pinned so that changes to train-bnn's defaults do not change this script's BNN.
  "$BIN/latentdrive" train-bnn "$OUT/data" "$OUT/bnn64" --epochs 6 --foreground-weight 10 \
    --set pretrain_epochs=1 --set lr=3e-3 --set lr_schedule=cosine --set num_threads=1 \
    --set loss=l2 --set road_weight=1 --set av_weight=1 --set val_every=1 \
    --set model.head_hidden=0 --set model.latent_norm=false -q
fi

train() {  # RUN MODE SCENARIO [extra args]
  local run=$1 mode=$2 scenario=$3; shift 3
  local resume=()
  [ -f "$run/checkpoint.safetensors" ] && resume=(--resume)
  "$BIN/latentdrive" train-policy "$run" --mode "$mode" --scenarios "$scenario" "${COMMON[@]}" "${resume[@]}" "$@"
}

for scenario in intersection merge; do
  train "$OUT/$scenario-raw" raw "$scenario"
  train "$OUT/$scenario-latent" latent "$scenario" --bnn "$OUT/bnn64"
  "$BIN/latentdrive" evaluate "$OUT/$scenario-latent" --compare "$OUT/$scenario-raw" --episodes "$EPISODES" \
    --json "$OUT/$scenario-eval.json" -q
  for mode in raw latent; do
    for ref in random rule; do
      "$BIN/latentdrive" evaluate "$OUT/$scenario-$mode" --compare "$ref" --policy none --episodes "$EPISODES" \
        --json "$OUT/$scenario-$mode-vs-$ref.json" -q
    done
  done
done
