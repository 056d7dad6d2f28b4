#!/usr/bin/env bash
# "Distinct goals" pilot (issue 19, docs/sim2real.md): is the instruction learnable by the tiny policy
# when episode goals are few, large, visually distinct categories (`data episodes -S
# goal_categories=[...]`; default: the six goal categories of Habitat's HM3D ObjectNav task, whose
# procedural hues lie >= 32 degrees apart)? BC with the right instructions against BC with shuffled
# ones (the instruction-blind control), both on exact renders of the same training houses, evaluated
# with the exact renderer on the pipeline's held-out houses under the same goal restriction.
# Not part of CI or the pipeline; a rerun reuses what exists under $O.
#
#   PATH=.venv/bin:$PATH bash scripts/distinct_goals_pilot.sh [OUT=/tmp/goals-pilot] [HOUSES=32] [SEED=0]
#   GOALS= bash scripts/distinct_goals_pilot.sh /tmp/route-pilot   # the default task (every category)
#
# Needs the sim2real pipeline's held-out captures (outputs/sim2real/captures/heldout). About 55 min on
# a 2-core CPU at the defaults (synth 6, episodes 8, the two BC runs side by side ~30, evaluations ~10).
set -euo pipefail
cd "$(dirname "$0")/.."
O=${1:-/tmp/goals-pilot}
HOUSES=${2:-32}
SEED=${3:-0}
GOALS=${GOALS-'["chair","bed","plant","toilet","tv","sofa"]'}  # GOALS= (empty): every category
RESTRICT=(); [ -n "$GOALS" ] && RESTRICT=(-S "goal_categories=$GOALS")
export WANDB_MODE=${WANDB_MODE:-disabled}
H=outputs/sim2real/captures/heldout
[ -e "$H" ] || { echo "missing $H: run dvc repro pipelines/sim2real/dvc.yaml:heldout_houses" >&2; exit 2; }
mkdir -p "$O"
stamp() { echo "[$(date +%T)] $*"; }

# The sim2real policy config with the pilots' BC budget (batch 16 x 1 500 steps), as the earlier pilots.
python - "$O/pilot.yaml" "$SEED" <<'EOF'
import sys
import yaml
cfg = yaml.safe_load(open("configs/navpolicy/sim2real.yaml"))
cfg["train"].update(batch_size=16, max_steps=1500, seed=int(sys.argv[2]))
yaml.safe_dump(cfg, open(sys.argv[1], "w"))
EOF

[ -d "$O/captures" ] || { stamp "synth $HOUSES houses"; image2sim data synth --scenes "$HOUSES" --seed 0 --noise middle --workers 2 --out "$O/captures"; }
[ -f "$O/episodes/shards.json" ] || { stamp "episodes (exact renders, 64 px, goals $GOALS)"; image2sim data episodes --scenes "$O/captures" \
  --out "$O/episodes" --render procedural --obs-height 64 --frame-stride 2 --workers 2 "${RESTRICT[@]}"; }
[ -f "$O/heldout/train/train.json.gz" ] || { stamp "held-out episodes"; image2sim data episodes --scenes "$H" \
  --out "$O/heldout" --render none --workers 2 "${RESTRICT[@]}"; }
shards=$(for d in "$O"/episodes/scenes/*/shard; do printf -- "--shard %s " "$d"; done)
stamp "BC: instructed and blind, side by side (1 thread each)"
# shellcheck disable=SC2086
[ -d "$O/bc/export" ] || image2sim nav train --stage bc --config "$O/pilot.yaml" $shards --out "$O/bc" --threads 1 > "$O/bc.log" 2>&1 &
# shellcheck disable=SC2086
[ -d "$O/blind/export" ] || image2sim nav train --stage bc --config "$O/pilot.yaml" --set data.shuffle_instructions=true \
  $shards --out "$O/blind" --threads 1 > "$O/blind.log" 2>&1 &
wait
for policy in bc blind; do
  [ -f "$O/eval/$policy.json" ] && continue
  stamp "evaluate $policy"
  image2sim eval nav --backend exact --scenes "$H" --episodes "$O/heldout/train/train.json.gz" \
    --agent image2nav --model "$O/$policy/export" --policy-config "$O/pilot.yaml" \
    --out "$O/eval/$policy" --metrics "$O/eval/$policy.json" --workers 2
done
[ -f "$O/eval/baselines.json" ] || image2sim eval nav --backend exact --scenes "$H" --episodes "$O/heldout/train/train.json.gz" \
  --agent random --agent forward --out "$O/eval/baselines" --metrics "$O/eval/baselines.json" --workers 2
stamp "done: $O/eval/{bc,blind,baselines}.json"
