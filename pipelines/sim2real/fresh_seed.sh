#!/usr/bin/env bash
# Issue 19's second check: the neural row's exported policy and the baselines on procedural houses of
# a seed the pipeline never used, with the data engine's default episode task and the exact renderer.
# Writes outputs/sim2real/fresh/{neural,baselines}.json (+ .protocol.json, + the agents' per-episode
# logs in fresh/<agent>/), which the report stage adds
# as checks.fresh_seed; then `dvc repro pipelines/sim2real/dvc.yaml:report` (or `make sim2real`).
#
#   bash pipelines/sim2real/fresh_seed.sh            # SEED=5000 HOUSES=3 WORKERS=2 POLICY=<export>
#
# Run from the repository root after `make sim2real`. Rerunning reuses the houses and the episodes.
set -euo pipefail
SEED=${SEED:-5000}; HOUSES=${HOUSES:-3}; WORKERS=${WORKERS:-2}
O=outputs/sim2real; W=${WORK:-$O/fresh_work}
POLICY=${POLICY:-$O/policies/neural/dagger/export}
CONFIG=${POLICY_CONFIG:-configs/navpolicy/sim2real.yaml}
[ -d "$POLICY" ] || { echo "error: no exported policy at $POLICY (run make sim2real first)" >&2; exit 2; }
[ -d "$W/captures/scene_$(printf %03d $((HOUSES - 1)))" ] \
  || image2sim data synth --scenes "$HOUSES" --seed "$SEED" --out "$W/captures" --workers "$WORKERS"
[ -f "$W/episodes/train/train.json.gz" ] \
  || image2sim data episodes --scenes "$W/captures" --out "$W/episodes" --render none --workers "$WORKERS"
evaluate() {  # <name> <agent args...>
  local name=$1; shift
  rm -rf "$W/$name"
  image2sim eval nav --backend exact --scenes "$W/captures" --episodes "$W/episodes/train/train.json.gz" \
    "$@" --workers "$WORKERS" --seed 0 --out "$W/$name" --metrics "$W/$name/nav.json"
}
evaluate neural --agent image2nav --model "$POLICY" --policy-config "$CONFIG"
evaluate baselines --agent random --agent forward
mkdir -p "$O/fresh"
for name in neural baselines; do
  cp "$W/$name/nav.json" "$O/fresh/$name.json.tmp" && mv "$O/fresh/$name.json.tmp" "$O/fresh/$name.json"
  if [ -f "$W/$name/nav.protocol.json" ]; then
    cp "$W/$name/nav.protocol.json" "$O/fresh/$name.protocol.json"
  fi
done
# The per-episode logs, beside the metrics files, for the report's paired comparison
# (<folder of the metrics file>/<agent>/*.jsonl).
for agent_dir in "$W"/neural/image2nav "$W"/baselines/random "$W"/baselines/forward; do
  agent=$(basename "$agent_dir")
  rm -rf "$O/fresh/$agent.tmp" && cp -r "$agent_dir" "$O/fresh/$agent.tmp"
  rm -rf "$O/fresh/$agent" && mv "$O/fresh/$agent.tmp" "$O/fresh/$agent"
done
echo "wrote $O/fresh/neural.json and $O/fresh/baselines.json (seed $SEED, $HOUSES houses)"
