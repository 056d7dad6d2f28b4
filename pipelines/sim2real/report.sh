#!/usr/bin/env bash
# The sim2real pipeline's last stage: gather every evaluation into metrics/sim2real.json,
# reports/sim2real.md and plots/sim2real_scaling.png (image2sim eval sim2real). Run from the repo root.
set -euo pipefail
O=outputs/sim2real
episodes_of() {  # training episodes behind a scaling point: the trajectories in its run's shards
  python3 - "$1" <<'PY'
import json, sys
from pathlib import Path

import yaml

cfg = yaml.safe_load(Path(sys.argv[1]).read_text())
n = sum(json.loads((Path(s) / "manifest.json").read_text())["num_trajectories"] for s in cfg["data"]["shards"])
print(min(n, cfg["data"].get("max_trajectories") or n))
PY
}
scaling=()
for d in "$O"/scaling/h*; do
  cfg="$d/bc/config.yaml"; [ -f "$cfg" ] || cfg="$d/config.yaml"   # hall: the neural row's BC run
  n_shards=$(python3 -c "import yaml,sys; print(len(yaml.safe_load(open(sys.argv[1]))['data']['shards']))" "$cfg")
  scaling+=(--scaling "$n_shards:$(episodes_of "$cfg")=image2nav@$d/nav.json")
done
# Data behind each training source: generated episodes and stored frames, DAgger episodes and frames,
# BC optimiser steps x batch (what the budget table reports as "frames seen").
python3 - "$O" <<'PY'
import json, sys
from pathlib import Path

import yaml

root = Path(sys.argv[1])
out = {}
for src in ("neural", "splat_only", "exact"):
    shards = sorted((root / "episodes" / src / "scenes").glob("*/shard"))
    dagger = sorted((root / "policies" / src / "dagger").glob("round_*/shard"))

    def count(paths):
        n = f = 0
        for s in paths:
            for line in (s / "trajectories.jsonl").read_text().splitlines():
                n += 1
                f += len(json.loads(line)["frame_steps"])
        return n, f

    n, f = count(shards)
    dn, df = count(dagger)
    cfg = yaml.safe_load((root / "policies" / src / "dagger" / "config.yaml").read_text())
    bc_steps = cfg["train"]["max_steps"]
    d = cfg["dagger"]
    out[src] = {
        "generated_episodes": n,
        "generated_frames": f,
        "dagger_episodes": dn,
        "dagger_frames": df,
        "bc_samples_seen": bc_steps * cfg["train"]["batch_size"],
        "dagger_samples_seen": d["rounds"] * d["train_steps_per_round"] * cfg["train"]["batch_size"],
        "max_observations_per_sample": cfg["data"]["max_observations"],
    }
(root / "budget").mkdir(exist_ok=True)
(root / "budget" / "data.json").write_text(json.dumps(out, indent=1) + "\n")
PY
# The unused-seed check (run by hand, docs/sim2real.md): rows read when their files exist.
checks=()
if [ -f "$O"/fresh/neural.json ] && [ -f "$O"/fresh/baselines.json ]; then
  checks=(--check fresh_seed/neural=image2nav@"$O"/fresh/neural.json
          --check fresh_seed/random=random@"$O"/fresh/baselines.json
          --check fresh_seed/forward=forward@"$O"/fresh/baselines.json)
fi
# Other training seeds of the trained rows (scripts/sim2real_seeds.sh, run by hand): read when
# present. The neural row's BC policies are a row of their own (neural_bc); the others' are not.
seeds=()
for row in neural splat_only exact; do
  for d in "$O"/seeds/"$row"_s*; do
    [ -f "$d/eval_dagger/nav.json" ] || continue
    s=${d##*/"$row"_s}
    seeds+=(--seed-run "$row/$s=image2nav@$d/eval_dagger/nav.json")
    if [ "$row" = neural ] && [ -f "$d/eval_bc/nav.json" ]; then
      seeds+=(--seed-run "neural_bc/$s=image2nav@$d/eval_bc/nav.json")
    fi
  done
done
budget=()
for f in "$O"/budget/*.json; do
  budget+=(--budget "$(basename "$f" .json)=$f")
done
image2sim eval sim2real \
  --row neural=image2nav@"$O"/eval/neural/nav.json \
  --row splat_only=image2nav@"$O"/eval/splat_only/nav.json \
  --row exact=image2nav@"$O"/eval/exact/nav.json \
  --row random=random@"$O"/eval/baselines/nav.json \
  --row forward=forward@"$O"/eval/baselines/nav.json \
  --row oracle=oracle@"$O"/eval/baselines/nav.json \
  --row neural_bc=image2nav@"$O"/scaling/hall/nav.json \
  --row blind=image2nav@"$O"/eval/blind/nav.json \
  --episode-logs neural_bc="$O"/scaling/hall/eval/image2nav \
  --policy neural="$O"/policies/neural/dagger/export \
  --policy splat_only="$O"/policies/splat_only/dagger/export \
  --policy exact="$O"/policies/exact/dagger/export \
  "${scaling[@]}" "${budget[@]}" ${checks[@]+"${checks[@]}"} ${seeds[@]+"${seeds[@]}"} \
  --episodes "$O"/heldout/train/train.json.gz \
  --header pipelines/sim2real/report_header.md \
  --out metrics/sim2real.json --report reports/sim2real.md --plot plots/sim2real_scaling.png
