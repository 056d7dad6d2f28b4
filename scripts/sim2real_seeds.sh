#!/usr/bin/env bash
# A trained row of a finished `make sim2real` (ROW: neural, the default, splat_only or exact),
# retrained with other training seeds on the same episodes and simulators (BC, then DAgger: the
# policy@ROW stage's commands with `--set train.seed=S`), each evaluated on the same held-out
# episodes with the exact backend (the eval@ROW stage's command). Prints every seed's SR and its
# paired comparison with forward, seed 0 being the pipeline's own policy.
#
#   [ROW=neural] bash scripts/sim2real_seeds.sh [OUT=outputs/sim2real/seeds] [SEEDS="1 2"]
#
# Needs outputs/sim2real from `make sim2real` (run from the repository root). ~8 min per seed on
# a 2-core CPU. In the default OUT, the pipeline's report reads the runs (`eval sim2real
# --seed-run`: every seed's SR, their mean and spread); then `dvc repro -s -f
# pipelines/sim2real/dvc.yaml:report`. docs/sim2real.md, "Three training seeds of the neural row".
set -euo pipefail
OUT=${1:-outputs/sim2real/seeds}
SEEDS=${2:-"1 2"}
ROW=${ROW:-neural}
O=outputs/sim2real
CONFIG=configs/navpolicy/sim2real.yaml
case $ROW in  # the policy@ROW stage's DAgger simulators (pipelines/sim2real/dvc.yaml)
  neural) SIM="--source neural --renderer $O/renderer/checkpoints/last.ckpt --sim-scenes $O/episodes/neural/scenes" ;;
  splat_only) SIM="--source splat_only --sim-scenes $O/episodes/splat_only/scenes" ;;
  exact) SIM="--source exact --sim-scenes $O/captures/train" ;;
  *) echo "error: ROW=$ROW: expected neural, splat_only or exact" >&2; exit 2 ;;
esac
[ -d "$O/episodes/$ROW/scenes" ] || { echo "error: $O/episodes/$ROW/scenes is missing: run make sim2real first" >&2; exit 2; }
mkdir -p "$OUT"
SHARDS=$(for d in "$O"/episodes/"$ROW"/scenes/*/shard; do printf -- "--shard %s " "$d"; done)
for seed in $SEEDS; do
  R=$OUT/${ROW}_s$seed
  if [ -f "$R/eval_dagger/nav.json" ]; then echo "seed $seed: done already ($R)"; continue; fi
  rm -rf "$R"
  # shellcheck disable=SC2086
  image2sim nav train --stage bc --config $CONFIG $SHARDS --out "$R/bc" --threads 2 --set train.seed=$seed --wandb disabled
  # shellcheck disable=SC2086
  image2sim nav train --stage dagger --config $CONFIG $SHARDS --init "$R/bc/export" \
    --episodes $O/episodes/$ROW/train/train.json.gz $SIM \
    --out "$R/dagger" --threads 2 --set train.seed=$seed --wandb disabled
  for stage in bc dagger; do
    image2sim eval nav --backend exact --scenes $O/captures/heldout --episodes $O/heldout/train/train.json.gz \
      --agent image2nav --model "$R/$stage/export" --policy-config $CONFIG --workers 2 --seed 0 \
      --out "$R/eval_$stage" --metrics "$R/eval_$stage/nav.json"
  done
done
python - "$OUT" "$SEEDS" "$ROW" <<'PY'
import sys
from pathlib import Path

from image2sim.eval.nav_summary import paired_success_comparison, wilson_interval
from image2sim.eval.sim2real import episode_successes

out, seeds, row = Path(sys.argv[1]), sys.argv[2].split(), sys.argv[3]
o = Path("outputs/sim2real")
forward = episode_successes(o / "eval/baselines/nav.json", "forward")
runs = {f"{row} s0": episode_successes(o / f"eval/{row}/nav.json", "image2nav")}
if row == "neural":  # the pipeline evaluates only the neural row's BC policy (the scaling curve's last point)
    runs["neural_bc s0"] = episode_successes(
        o / "scaling/hall/nav.json", "image2nav", o / "scaling/hall/eval/image2nav"
    )
for s in seeds:
    runs[f"{row} s{s}"] = episode_successes(out / f"{row}_s{s}/eval_dagger/nav.json", "image2nav")
    runs[f"{row}_bc s{s}"] = episode_successes(out / f"{row}_s{s}/eval_bc/nav.json", "image2nav")
print(f"forward: SR {100 * sum(forward.values()) / len(forward):.1f} ({len(forward)} episodes)")
for name, succ in runs.items():
    k, n = sum(succ.values()), len(succ)
    lo, hi = wilson_interval(k, n)
    c = paired_success_comparison(succ, forward)
    d, (dlo, dhi) = 100 * c["sr_difference"], (100 * x for x in c["difference_ci"])
    print(f"{name:14s} SR {100 * k / n:5.1f} [{100 * lo:.1f}, {100 * hi:.1f}]  "
          f"vs forward {d:+.1f} [{dlo:+.1f}, {dhi:+.1f}] McNemar p {c['mcnemar_p']:.2f}")
PY
