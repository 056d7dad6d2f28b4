#!/usr/bin/env bash
# Is the tiny pixel-flow renderer limited by its training length? (issue 20; docs/renderer.md,
# "Training length on a GPU"). The same three procedural houses as scripts/renderer_ablation.sh
# (noise tier `middle`, 16 panoramas of 128x256 each), identity Gaussians, the `tiny` preset with its
# whole curriculum scaled to each STEPS value (`sim train --steps`), seed 0; each renderer scored
# with `eval render --condition-source gaussians` on the held-out panoramas (every 8th frame), one
# step, against the exact renderer, beside splat_only and splat_fill.
#
#   O=<work dir> STEPS="400 1600 4800" ACCEL=gpu J=<cores> bash scripts/renderer_steps_pilot.sh
#
# The first STEPS value trains alone (it builds the condition cache); the others then train side by
# side (one GPU holds them all at batch 2), each scored as soon as it is trained. Finished steps are
# skipped on a rerun. Results: $O/eval_<steps>.json and $O/summary.json; progress in $O/progress.log;
# COPY_TO=<dir> (e.g. a device call's $OUT) receives each result as it lands, so a run stopped by a
# time limit keeps what it finished. On a lent H100 (2026-11-27) the 400-step run took 146 s with its
# conditions, and the 1600-step run 310 s beside a 3200-step one (5.8 steps/s): the tiny renderer at
# batch 2 is launch-bound there, about 4x this 2-core CPU's rate.
set -u
O=${O:-outputs/renderer_steps}; STEPS=${STEPS:-"400 1600 4800"}; ACCEL=${ACCEL:-cpu}; J=${J:-$(nproc)}
export WANDB_MODE=${WANDB_MODE:-disabled}
mkdir -p "$O"
log() { echo "[$(date +%T)] $*" | tee -a "$O/progress.log"; }
[ -d "$O/synth/scene_002" ] || image2sim data synth --out "$O/synth" --scenes 3 --views 16 --preset tiny \
  --height 128 --width 256 --noise middle --seed 0 --workers 3 --overwrite > "$O/synth.log" 2>&1
D=(); for s in "$O"/synth/scene_*; do D+=(--data "$s"); done
log "captures: ${#D[@]} args"
train() {  # steps
  [ -f "$O/run_$1/checkpoints/last.ckpt" ] && return 0
  rm -rf "$O/run_$1"
  local t0=$SECONDS
  image2sim sim train --config tiny --steps "$1" "${D[@]}" --holdout-every 8 --seed 0 --accelerator "$ACCEL" \
    --splat-cache "$O/cache" --data-workers "$J" --checkpoint-every "$1" --grid-every "$1" --out "$O/run_$1" \
    > "$O/train_$1.log" 2>&1 && log "trained $1 steps in $((SECONDS - t0)) s" || log "FAILED train $1"
}
evaluate() {  # steps
  [ -f "$O/eval_$1.json" ] && return 0
  image2sim eval render --checkpoint "$O/run_$1/checkpoints/last.ckpt" --config tiny --condition-source gaussians \
    "${D[@]}" --holdout-every 8 --steps 1 --runs 3 --out "$O/eval_$1.json" --plot "$O/eval_$1.png" \
    > "$O/eval_$1.log" 2>&1 && log "evaluated $1" || log "FAILED eval $1"
  [ -n "${COPY_TO:-}" ] && cp "$O/eval_$1.json" "$O/progress.log" "$COPY_TO/" 2>/dev/null
  return 0
}
set -- $STEPS
train "$1"
evaluate "$1" &
shift
for s in "$@"; do (train "$s" && evaluate "$s") & done
wait
python - "$O" <<'PY'
import json, pathlib, re, sys
o = pathlib.Path(sys.argv[1])
rows = {}
for f in o.glob("eval_*.json"):
    m = re.fullmatch(r"eval_(\d+)\.json", f.name)
    if not m:
        continue
    methods = json.loads(f.read_text())["methods"]
    log = (o / "progress.log").read_text()
    took = re.search(rf"trained {m[1]} steps in (\d+) s", log)
    rows[int(m[1])] = {
        "train_s": int(took[1]) if took else None,
        **{k: {"psnr": round(v["psnr"], 3), "ssim": round(v["ssim"], 4), "depth_absrel": round(v["depth_absrel"], 4)}
           for k, v in methods.items()},
    }
rows = dict(sorted(rows.items()))
(o / "summary.json").write_text(json.dumps(rows, indent=1))
print(json.dumps(rows, indent=1))
PY
log "done"
