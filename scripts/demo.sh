#!/usr/bin/env bash
# The main job (`make demo`): reproduce the pipeline in dvc.yaml on the active profile (params.yaml),
# add the real HM3D sample when ../shared/data is present, and print where everything is.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"
export DVC_NO_ANALYTICS=1 HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 WANDB_MODE="${WANDB_MODE:-offline}"
start=$(date +%s)

profile=$(python3 -c "import yaml,sys; print(yaml.safe_load(open('params.yaml'))['profile'])" 2>/dev/null || echo "?")
echo "== Image2Sim demo: dvc repro on profile '$profile' =="
dvc repro

# Real data: read in place, never copied. Outputs go to outputs/real/ (not tracked).
shared="${IMAGE2SIM_SHARED_DATA:-../shared/data}"
if [ -d "$shared/hm3d_360" ]; then
  mkdir -p outputs/real
  for scene in "$shared"/hm3d_360/*/; do
    name=$(basename "$scene")
    echo "== real capture: $name (HM3D sample, read in place) =="
    image2sim data inspect "$scene" --max-frames 8
    if [ ! -f "outputs/real/$name.ply" ]; then
      image2sim data fuse "$scene" --stride 4 --voxel 0.05 --out "outputs/real/$name.ply"
    fi
  done
else
  echo "(no real sample at $shared/hm3d_360: skipping the HM3D part)"
fi

echo "== inspection of the first procedural scene =="
first=$(ls -d data/synthetic/scene_* | head -n 1)
image2sim data inspect "$first" --max-frames 4

echo "== outputs =="
echo "point clouds:  $(ls outputs/clouds/*.ply | tr '\n' ' ')"
[ -d outputs/real ] && echo "real clouds:   $(ls outputs/real/*.ply | tr '\n' ' ')" || true
echo "scenes:        outputs/scenes/ (Gaussians + navigation maps; top-down PNGs in outputs/navmaps/)"
echo "episodes:      outputs/episodes/ ; renderer: outputs/renderer/ ; policy: outputs/nav/"
echo "model card:    outputs/policy_card/README.md (the policy's card with metrics/nav.json)"
echo "metrics:       metrics/render.json metrics/nav.json ; report: reports/pipeline/ ; plot: plots/render_speed.png"
echo
cat reports/pipeline/render.md
echo
cat reports/pipeline/nav.md
echo "demo finished in $(( $(date +%s) - start )) s"
