#!/usr/bin/env bash
# Table 4 of the seed paper with learned feature Gaussians and several training seeds (issue 20,
# item 3; docs/renderer.md "Table 4 with learned features").
#
#   PATH=.venv/bin:$PATH bash scripts/renderer_ablation.sh [OUT=/tmp/renderer-ablation] [SEEDS="0 1"] [ENCODER_STEPS=100]
#
# ENCODER_CONFIG=configs/gaussians/tiny_labels.yaml gives stage 1 the captures' per-pixel categories
# as its semantic target (train.w_labels); the default `tiny` has none without DINOv3 weights.
#
# 1. three procedural houses (noise tier `middle`, 16 panoramas of 128x256 each, as in
#    reports/renderer_tiny.md's Table-4 run);
# 2. the stage-1 encoder (`sim train-geometry`, ENCODER_STEPS steps), frozen afterwards;
# 3. per seed: the renderer with the 400-step session curriculum on splats of the encoder's feature
#    Gaussians (`--encoder`), the three Table-4 ablations (no_semantic, no_alpha_gate, no_distill)
#    the same way, and the full renderer on identity Gaussians (zero features) for comparison;
# 4. per seed: `eval render --condition-source gaussians` on the held-out panoramas (every 8th
#    frame), one step, with splat_only (= w/o pixel flow) and splat_fill as references;
# 5. `scripts/renderer_ablation_report.py` writes reports/renderer_ablation.{md,json}.
#
# Everything lands under $OUT; finished steps are skipped, so a rerun continues. About 75 min on a
# 2-core CPU for two seeds (each renderer run ~5 min, the encoder ~7 min, each evaluation ~3 min).
set -euo pipefail
cd "$(dirname "$0")/.."
O=${1:-/tmp/renderer-ablation}
SEEDS=${2:-"0 1"}
ENCODER_STEPS=${3:-100}
ENCODER_CONFIG=${ENCODER_CONFIG:-tiny}
export WANDB_MODE=${WANDB_MODE:-disabled}
mkdir -p "$O"
stamp() { echo "[$(date +%T)] $*"; }

[ -d "$O/synth/scene_002" ] || { stamp "synth"; image2sim data synth --out "$O/synth" --scenes 3 --views 16 \
  --preset tiny --height 128 --width 256 --noise middle --seed 0 --overwrite; }
D=()
for s in "$O"/synth/scene_*; do D+=(--data "$s"); done
ENC="$O/encoder/encoder.safetensors"
[ -f "$ENC" ] || { stamp "stage-1 encoder ($ENCODER_STEPS steps)"; rm -rf "$O/encoder"; \
  image2sim sim train-geometry "$O"/synth/scene_* --config "$ENCODER_CONFIG" --steps "$ENCODER_STEPS" --out "$O/encoder" >/dev/null; }

train() {  # seed name config encoder
  local run="$O/run/seed$1/$2"
  [ -f "$run/checkpoints/last.ckpt" ] && return 0
  stamp "train seed $1 $2"
  rm -rf "$run"
  image2sim sim train --config "$3" "${D[@]}" --encoder "$4" --seed "$1" --holdout-every 8 \
    --out "$run" --splat-cache "$O/cache" --checkpoint-every 400 --grid-every 400 >"$O/train_seed$1_$2.log" 2>&1
}

for seed in $SEEDS; do
  train "$seed" main configs/renderer/tiny_session.yaml "$ENC"
  for switch in no_semantic no_alpha_gate no_distill; do
    train "$seed" "$switch" "configs/renderer/tiny_ablation_$switch.yaml" "$ENC"
  done
  train "$seed" identity configs/renderer/tiny_session.yaml identity
  R="$O/run/seed$seed"
  [ -f "$O/eval/seed$seed.json" ] || { stamp "eval seed $seed (learned features)"; \
    image2sim eval render --checkpoint "$R/main/checkpoints/last.ckpt" --config configs/renderer/tiny_session.yaml \
      --condition-source gaussians "${D[@]}" --holdout-every 8 --steps 1 --encoder "$ENC" \
      --ablation "no_semantic=$R/no_semantic/checkpoints/last.ckpt" \
      --ablation "no_alpha_gate=$R/no_alpha_gate/checkpoints/last.ckpt" \
      --ablation "no_distill=$R/no_distill/checkpoints/last.ckpt" \
      --out "$O/eval/seed$seed.json" >"$O/eval_seed$seed.log" 2>&1; }
  [ -f "$O/eval/seed${seed}_identity.json" ] || { stamp "eval seed $seed (identity Gaussians)"; \
    image2sim eval render --checkpoint "$R/identity/checkpoints/last.ckpt" --config configs/renderer/tiny_session.yaml \
      --condition-source gaussians "${D[@]}" --holdout-every 8 --steps 1 --encoder identity \
      --out "$O/eval/seed${seed}_identity.json" >"$O/eval_seed${seed}_identity.log" 2>&1; }
done
stamp "report"
python scripts/renderer_ablation_report.py "$O" --encoder-steps "$ENCODER_STEPS" --encoder-config "$ENCODER_CONFIG"
