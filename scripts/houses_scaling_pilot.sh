#!/usr/bin/env bash
# Houses-scaling and policy-capacity pilots of docs/sim2real.md (issue 19), sized for one machine with
# many cores (and optionally a GPU): BC policies on the exact renders of procedural training houses
# (noise tier `middle`), evaluated with the exact renderer on the sim2real pipeline's held-out houses
# (seeds 1000..) and, unless FRESH=0, on houses of an unused seed (5000..).
#
#   W=<work dir> N=64 J=<cores> CONFIG=<policy yaml> ACCEL=gpu bash scripts/houses_scaling_pilot.sh
#
# POLICIES lists the policies, each name:seed:blind:houses:variant -- houses `A` = houses 0..31 (they
# train while the rest render), `AB` = all N; blind 1 = shuffled instructions (the instruction-blind
# control); variant names extra `--set`s in VARIANT_<variant> (`base`: none). SETS applies to every
# policy (e.g. "--set train.batch_size=32 --set train.max_minutes=3"). The default is the houses
# pilot: h32 (houses 0..31), hN, hN_s1 (seed 1) and hN_blind. The capacity pilot:
#   N=32 FRESH=0 POLICIES="tiny:0:0:A:base tiny_blind:0:1:A:base large:0:0:A:large large_blind:0:1:A:large"
#
# Measured on a lent H100 machine (16 cores, 2026-11-26): 64 houses synthesised in 3.7 min, episodes
# 1.9 min per 32 houses. On a device whose ignored folders do not survive between calls, run it in ONE
# call (setsid ... &, poll, and set COPY_TO=$OUT: every result and the progress log are copied there as
# they land, so a call stopped by its time limit keeps what finished). Set MAX_EPISODES for a smoke
# run. Policies: <W>/bc_<name>; metrics: <W>/results/*.json and summary.json; progress with
# timestamps in <W>/progress.log. Rerunning skips what is done (captures, shards, exports).
set -u
W=${W:-outputs/houses_pilot}; N=${N:-64}; J=${J:-$(nproc)}; ACCEL=${ACCEL:-cpu}
CONFIG=${CONFIG:-configs/navpolicy/sim2real.yaml}; HELDOUT_SEED=${HELDOUT_SEED:-1000}; FRESH_SEED=${FRESH_SEED:-5000}
TRAIN_THREADS=${TRAIN_THREADS:-3}; MAX_EPISODES=${MAX_EPISODES:-100000}; REFERENCE=${REFERENCE:-}
FRESH=${FRESH:-1}; SETS=${SETS:-}; COPY_TO=${COPY_TO:-}; VARIANT_base=""
VARIANT_large=${VARIANT_large:-"--set model.tiny.text_hidden_size=192 --set model.tiny.text_layers=4 \
  --set model.tiny.text_head_dim=32 --set model.tiny.mrope_section=[4,6,6] --set model.tiny.text_intermediate_size=512 \
  --set model.tiny.vision_hidden_size=96 --set model.tiny.vision_layers=4 --set model.tiny.vision_heads=4 \
  --set model.tiny.vision_intermediate_size=256 --set model.freeze_vision=false"}
POLICIES=${POLICIES:-"h32:0:0:A:base h$N:0:0:AB:base h${N}_s1:1:0:AB:base h${N}_blind:0:1:AB:base"}
# episode files to evaluate on (default: the data engine's default task on the regenerated houses;
# pass earlier files, e.g. the pipeline's outputs/sim2real/heldout/train/train.json.gz, to compare)
HELDOUT_EPISODES=${HELDOUT_EPISODES:-$W/heldout_eps/train/train.json.gz}; FRESH_EPISODES=${FRESH_EPISODES:-$W/fresh_eps/train/train.json.gz}
mkdir -p "$W/results"
log() {
  echo "[$(date +%T)] $*" | tee -a "$W/progress.log"
  [ -n "$COPY_TO" ] && cp -f "$W/progress.log" "$W"/results/*.json "$COPY_TO"/ 2>/dev/null; true
}
episodes() {  # <captures> <out> <workers> [extra]
  [ -f "$2/shards.json" ] || image2sim data episodes --scenes "$1" --out "$2" --workers "$3" "${@:4}" > "$2.log" 2>&1
}
train() {  # <name> <seed> <shuffle> <variant> <shards json>...
  local name=$1 seed=$2 shuffle=$3 variant=VARIANT_$4; shift 4
  [ -d "$W/bc_$name/export" ] && return 0
  local args=()
  for f in "$@"; do
    for s in $(python3 -c "import json,sys; print(' '.join(json.load(open(sys.argv[1]))['shards']))" "$f"); do
      args+=(--shard "$(dirname "$f")/$s"); done; done
  log "train $name (${#args[@]} shard args)"
  local blind=false; [ "$shuffle" = 1 ] && blind=true
  image2sim nav train --stage bc --config "$CONFIG" --set train.seed="$seed" --set data.shuffle_instructions=$blind \
    --set train.accelerator="$ACCEL" --set train.devices=1 ${!variant} $SETS "${args[@]}" --out "$W/bc_$name" \
    --threads "$TRAIN_THREADS" > "$W/bc_$name.log" 2>&1 \
    && log "trained $name: $(grep -o '"global_step": [0-9]*' "$W/bc_$name.log")" || log "FAILED train $name"
}
evaluate() {  # <name> <model dir> <policy yaml> (name `baselines`: random and forward, no model)
  local eps agents
  local sets=heldout; [ "$FRESH" = 1 ] && sets="heldout fresh"
  for set in $sets; do
    [ -f "$W/results/${1}_$set.json" ] && continue
    [ $set = heldout ] && eps=$HELDOUT_EPISODES || eps=$FRESH_EPISODES
    agents=(--agent image2nav --model "$2" --policy-config "$3")
    [ "$1" = baselines ] && agents=(--agent random --agent forward)
    OMP_NUM_THREADS=1 image2sim eval nav --backend exact --scenes "$W/${set}_caps" --episodes "$eps" \
      "${agents[@]}" --out "$W/eval_${1}_$set" \
      --metrics "$W/results/${1}_$set.json" --workers 3 --max-episodes "$MAX_EPISODES" > "$W/eval_${1}_$set.log" 2>&1 \
      && log "evaluated $1 on $set" || log "FAILED eval $1 $set"
  done
}

log "start: N=$N J=$J accel=$ACCEL"
# the evaluation houses and their episodes in the background, beside the training houses
SPLITS="heldout:$HELDOUT_SEED"; [ "$FRESH" = 1 ] && SPLITS="$SPLITS fresh:$FRESH_SEED"
(for s in $SPLITS; do
  [ -d "$W/${s%%:*}_caps/scene_002" ] || image2sim data synth --scenes 3 --seed "${s##*:}" --out "$W/${s%%:*}_caps" --workers 3 > "$W/synth_${s%%:*}.log" 2>&1
  episodes "$W/${s%%:*}_caps" "$W/${s%%:*}_eps" 3 --render none
done; log "evaluation houses and episodes done") &
[ -d "$W/caps/scene_$(printf %03d $((N-1)))" ] || image2sim data synth --scenes "$N" --seed 0 --noise middle \
  --out "$W/caps" --workers "$J" > "$W/synth.log" 2>&1
log "training captures done"
# the first 32 houses and the rest as two episode runs, so h32 trains while the rest renders
mkdir -p "$W/capsA" "$W/capsB"
for d in "$W"/caps/scene_*; do i=$((10#${d##*_})); [ $i -lt 32 ] && t=capsA || t=capsB; ln -sfn "../caps/${d##*/}" "$W/$t/${d##*/}"; done
RENDER=(--render procedural --obs-height 64 --frame-stride 2)
episodes "$W/capsA" "$W/epsA" "$J" "${RENDER[@]}"; log "episodes of houses 0..31 done"
launch() {  # train every policy of POLICIES on houses $1 (A or AB)
  local spec name seed blind houses variant shards
  for spec in $POLICIES; do
    IFS=: read -r name seed blind houses variant <<< "$spec"
    [ "$houses" = "$1" ] || continue
    shards=("$W/epsA/shards.json"); [ "$houses" = AB ] && shards+=("$W/epsB/shards.json")
    train "$name" "$seed" "$blind" "${variant:-base}" "${shards[@]}" &
  done
}
launch A
if [ "$N" -gt 32 ]; then
  episodes "$W/capsB" "$W/epsB" "$J" "${RENDER[@]}"; log "episodes of houses 32..$((N-1)) done"
  launch AB
fi
# a policy trained elsewhere on the same task (REFERENCE=<export>): the same evaluation, here
[ -n "$REFERENCE" ] && evaluate ref "$REFERENCE" "$CONFIG"
wait  # the trainings and the evaluation houses
# every policy's evaluations at once (eval nav parallelises over the 3 scenes only), each with the
# config it trained with; the baselines beside them
for d in "$W"/bc_*/export; do n=$(basename "$(dirname "$d")"); evaluate "${n#bc_}" "$d" "$(dirname "$d")/config.yaml" & done
evaluate baselines "" "" &
wait
python3 - "$W" <<'PY'
import json, pathlib, sys
w = pathlib.Path(sys.argv[1])
rows = {}
for f in sorted([*(w / "results").glob("*_heldout.json"), *(w / "results").glob("*_fresh.json")]):
    name, _, split = f.stem.rpartition("_")
    for agent, a in json.loads(f.read_text())["agents"].items():
        row = name if agent == "image2nav" else agent
        rows.setdefault(row, {})[split] = {"sr": round(100 * a["sr"], 1), "sr_ci": [round(100 * c, 1) for c in a["sr_ci"]]}
(w / "results" / "summary.json").write_text(json.dumps(rows, indent=1))
print(json.dumps(rows, indent=1))
PY
log "done: $(tr -d ' \n' < "$W/results/summary.json")"
