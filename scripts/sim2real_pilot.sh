#!/usr/bin/env bash
# Sim-to-real policy pilot (issue 19, docs/sim2real.md "Pilots"): more training houses and a larger
# DAgger budget than `make sim2real` affords, on exact renders (the `exact` row's observation source),
# evaluated on the pipeline's held-out houses and on houses of an unused seed, with the exact renderer.
# Not part of CI or the pipeline; it reuses what exists under $O, so a rerun continues (DAgger resumes).
#
#   PATH=.venv/bin:$PATH bash scripts/sim2real_pilot.sh [OUT=/tmp/s2r-pilot] [HOUSES=32] [ROUNDS=5]
#
# Needs the sim2real pipeline's held-out houses and episodes (outputs/sim2real/captures/heldout,
# outputs/sim2real/heldout: `dvc repro pipelines/sim2real/dvc.yaml:heldout_episodes`). About 2.5 h on
# a 2-core CPU at the defaults (synth 6 min, episodes 8 min, BC 15 min, DAgger ~8-20 min per round,
# each evaluation 2-10 min), most of it DAgger.
set -euo pipefail
cd "$(dirname "$0")/.."
O=${1:-/tmp/s2r-pilot}
HOUSES=${2:-32}
ROUNDS=${3:-5}
FRESH_SEED=5000
export WANDB_MODE=${WANDB_MODE:-disabled}
H=outputs/sim2real
for need in "$H/captures/heldout" "$H/heldout/train/train.json.gz"; do
  [ -e "$need" ] || { echo "missing $need: run dvc repro pipelines/sim2real/dvc.yaml:heldout_episodes" >&2; exit 2; }
done
mkdir -p "$O"
stamp() { echo "[$(date +%T)] $*"; }

# The sim2real policy config with the pilot's budget: batch 16 (BC 1 500 steps = 24k samples), DAgger
# with 64 episodes and 300 updates per round, model share 0.5 -> 0.9.
python - "$O/pilot.yaml" "$ROUNDS" <<'EOF'
import sys
import yaml
cfg = yaml.safe_load(open("configs/navpolicy/sim2real.yaml"))
cfg["train"].update(batch_size=16, max_steps=1500)
cfg["dagger"].update(rounds=int(sys.argv[2]), episodes_per_round=64, train_steps_per_round=300,
                     model_probability=0.5, final_model_probability=0.9)
yaml.safe_dump(cfg, open(sys.argv[1], "w"))
EOF

[ -d "$O/captures" ] || { stamp "synth $HOUSES houses"; image2sim data synth --scenes "$HOUSES" --seed 0 --noise middle --out "$O/captures"; }
[ -f "$O/episodes/shards.json" ] || { stamp "episodes (exact renders, 64 px)"; image2sim data episodes --scenes "$O/captures" \
  --out "$O/episodes" --render procedural --obs-height 64 --frame-stride 2 --workers 2; }
shards=$(for d in "$O"/episodes/scenes/*/shard; do printf -- "--shard %s " "$d"; done)
# shellcheck disable=SC2086
[ -d "$O/bc/export" ] || { stamp "BC"; image2sim nav train --stage bc --config "$O/pilot.yaml" $shards --out "$O/bc" --threads 2; }
stamp "DAgger ($ROUNDS rounds)"
# shellcheck disable=SC2086
image2sim nav train --stage dagger --config "$O/pilot.yaml" $shards --init "$O/bc/export" \
  --episodes "$O/episodes/train/train.json.gz" --source exact --sim-scenes "$O/captures" --out "$O/dagger" --threads 2

[ -d "$O/fresh" ] || image2sim data synth --scenes 3 --seed $FRESH_SEED --out "$O/fresh"
[ -f "$O/fresh-eps/train/train.json.gz" ] || image2sim data episodes --scenes "$O/fresh" --out "$O/fresh-eps" --render none --workers 2
for policy in bc dagger; do
  stamp "evaluate $policy"
  image2sim eval nav --backend exact --scenes "$H/captures/heldout" --episodes "$H/heldout/train/train.json.gz" \
    --agent image2nav --model "$O/$policy/export" --policy-config "$O/pilot.yaml" \
    --out "$O/eval/$policy" --metrics "$O/eval/$policy.json" --workers 2
  image2sim eval nav --backend exact --scenes "$O/fresh" --episodes "$O/fresh-eps/train/train.json.gz" \
    --agent image2nav --model "$O/$policy/export" --policy-config "$O/pilot.yaml" \
    --out "$O/eval/fresh-$policy" --metrics "$O/eval/fresh-$policy.json" --workers 2
done
image2sim eval nav --backend exact --scenes "$O/fresh" --episodes "$O/fresh-eps/train/train.json.gz" \
  --agent random --agent forward --out "$O/eval/fresh-baselines" --metrics "$O/eval/fresh-baselines.json" --workers 2
stamp "done: $O/eval/*.json (held-out baselines: $H/eval/baselines/nav.json)"
