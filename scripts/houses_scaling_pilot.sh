#!/usr/bin/env bash
# Houses-scaling pilot of docs/sim2real.md (issue 19), sized for one machine with many cores (and
# optionally a GPU): BC policies on the exact renders of the first 32 and of all N procedural training
# houses (noise tier `middle`), the same policy config and budget, evaluated with the exact renderer
# on the sim2real pipeline's held-out houses (seeds 1000..) and on houses of an unused seed (5000..).
#
#   W=<work dir> N=64 J=<cores> CONFIG=<policy yaml> ACCEL=gpu bash scripts/houses_scaling_pilot.sh
#
# Measured on a lent H100 machine (16 cores, 2026-11-26): 64 houses synthesised in 3.7 min, episodes
# 1.9 min per 32 houses; training time not yet measured. On a device whose ignored folders do not
# survive between calls, run it in ONE call (setsid ... &, poll, copy $W/results and
# $W/progress.log to $OUT before the call returns). Set MAX_EPISODES for a smoke run. Policies (each <W>/bc_<name>): h32 (houses 0..31, seed 0), hN (all N, seed 0), hN_s1 (all N, seed 1),
# hN_blind (all N, instructions shuffled: the instruction-blind control). Metrics: <W>/results/*.json;
# progress with timestamps in <W>/progress.log. Rerunning skips what is done (captures, shards, exports).
set -u
W=${W:-outputs/houses_pilot}; N=${N:-64}; J=${J:-$(nproc)}; ACCEL=${ACCEL:-cpu}
CONFIG=${CONFIG:-configs/navpolicy/sim2real.yaml}; HELDOUT_SEED=${HELDOUT_SEED:-1000}; FRESH_SEED=${FRESH_SEED:-5000}
TRAIN_THREADS=${TRAIN_THREADS:-3}; MAX_EPISODES=${MAX_EPISODES:-100000}; REFERENCE=${REFERENCE:-}
# episode files to evaluate on (default: the data engine's default task on the regenerated houses;
# pass earlier files, e.g. the pipeline's outputs/sim2real/heldout/train/train.json.gz, to compare)
HELDOUT_EPISODES=${HELDOUT_EPISODES:-$W/heldout_eps/train/train.json.gz}; FRESH_EPISODES=${FRESH_EPISODES:-$W/fresh_eps/train/train.json.gz}
mkdir -p "$W/results"
log() { echo "[$(date +%T)] $*" | tee -a "$W/progress.log"; }
episodes() {  # <captures> <out> <workers> [extra]
  [ -f "$2/shards.json" ] || image2sim data episodes --scenes "$1" --out "$2" --workers "$3" "${@:4}" > "$2.log" 2>&1
}
train() {  # <name> <seed> <shuffle> <shards json>...
  local name=$1 seed=$2 shuffle=$3; shift 3
  [ -d "$W/bc_$name/export" ] && return 0
  local args=()
  for f in "$@"; do
    for s in $(python -c "import json,sys; print(' '.join(json.load(open(sys.argv[1]))['shards']))" "$f"); do
      args+=(--shard "$(dirname "$f")/$s"); done; done
  log "train $name (${#args[@]} shard args)"
  local blind=false; [ "$shuffle" = 1 ] && blind=true
  image2sim nav train --stage bc --config "$CONFIG" --set train.seed="$seed" --set data.shuffle_instructions=$blind \
    --set train.accelerator="$ACCEL" --set train.devices=1 "${args[@]}" --out "$W/bc_$name" \
    --threads "$TRAIN_THREADS" > "$W/bc_$name.log" 2>&1 && log "trained $name" || log "FAILED train $name"
}
evaluate() {  # <name> <model dir> <policy yaml>
  local eps
  for set in heldout fresh; do
    [ -f "$W/results/${1}_$set.json" ] && continue
    [ $set = heldout ] && eps=$HELDOUT_EPISODES || eps=$FRESH_EPISODES
    image2sim eval nav --backend exact --scenes "$W/${set}_caps" --episodes "$eps" \
      --agent image2nav --model "$2" --policy-config "$3" --out "$W/eval_${1}_$set" \
      --metrics "$W/results/${1}_$set.json" --workers 3 --max-episodes "$MAX_EPISODES" > "$W/eval_${1}_$set.log" 2>&1 \
      && log "evaluated $1 on $set" || log "FAILED eval $1 $set"
  done
}

log "start: N=$N J=$J accel=$ACCEL"
[ -d "$W/caps/scene_$(printf %03d $((N-1)))" ] || image2sim data synth --scenes "$N" --seed 0 --noise middle \
  --out "$W/caps" --workers "$J" > "$W/synth.log" 2>&1
for s in heldout:$HELDOUT_SEED fresh:$FRESH_SEED; do
  [ -d "$W/${s%%:*}_caps/scene_002" ] || image2sim data synth --scenes 3 --seed "${s##*:}" --out "$W/${s%%:*}_caps" --workers 3 > "$W/synth_${s%%:*}.log" 2>&1
  episodes "$W/${s%%:*}_caps" "$W/${s%%:*}_eps" 3 --render none
done
log "captures done"
# the first 32 houses and the rest as two episode runs, so h32 trains while the rest renders
mkdir -p "$W/capsA" "$W/capsB"
for d in "$W"/caps/scene_*; do i=$((10#${d##*_})); [ $i -lt 32 ] && t=capsA || t=capsB; ln -sfn "../caps/${d##*/}" "$W/$t/${d##*/}"; done
RENDER=(--render procedural --obs-height 64 --frame-stride 2)
episodes "$W/capsA" "$W/epsA" "$J" "${RENDER[@]}"; log "episodes of houses 0..31 done"
train h32 0 0 "$W/epsA/shards.json" &
if [ "$N" -gt 32 ]; then
  episodes "$W/capsB" "$W/epsB" "$J" "${RENDER[@]}"; log "episodes of houses 32..$((N-1)) done"
  train h$N 0 0 "$W/epsA/shards.json" "$W/epsB/shards.json" &
  train h${N}_s1 1 0 "$W/epsA/shards.json" "$W/epsB/shards.json" &
  train h${N}_blind 0 1 "$W/epsA/shards.json" "$W/epsB/shards.json" &
fi
# a policy trained elsewhere on the same task (REFERENCE=<export>): the same evaluation, here
[ -n "$REFERENCE" ] && evaluate ref "$REFERENCE" "$CONFIG"
wait
# every policy's two evaluations at once (eval nav parallelises over the 3 scenes only)
for d in "$W"/bc_*/export; do n=$(basename "$(dirname "$d")"); evaluate "${n#bc_}" "$d" "$CONFIG" & done
wait
python - "$W" <<'PY'
import json, pathlib, sys
w = pathlib.Path(sys.argv[1])
rows = {}
for f in sorted([*(w / "results").glob("*_heldout.json"), *(w / "results").glob("*_fresh.json")]):
    name, _, split = f.stem.rpartition("_")
    a = json.loads(f.read_text())["agents"]["image2nav"]
    rows.setdefault(name, {})[split] = {"sr": round(100 * a["sr"], 1), "sr_ci": [round(100 * c, 1) for c in a["sr_ci"]]}
(w / "results" / "summary.json").write_text(json.dumps(rows, indent=1))
print(json.dumps(rows, indent=1))
PY
log "done"
