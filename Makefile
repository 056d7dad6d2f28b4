# Image2Sim — the two commands a newcomer needs are `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# Keep the machine-wide cap (if any) and pin torch for every install, also inside sdist builds.
PIP_CONSTRAINT := $(CURDIR)/constraints.txt $(wildcard /etc/xdg/pip/constraints.txt)
export PIP_CONSTRAINT
export PIP_DISABLE_PIP_VERSION_CHECK := 1
export HF_HUB_OFFLINE := 1
export TRANSFORMERS_OFFLINE := 1
export DVC_NO_ANALYTICS := 1
export WANDB_MODE ?= offline

PACKAGES := packages/simulator packages/dataengine packages/navpolicy packages/eval
STAMP := $(VENV)/.image2sim-setup
SETUP_INPUTS := constraints.txt requirements-dev.txt requirements-pipeline.txt $(addsuffix /pyproject.toml,$(PACKAGES))

.PHONY: setup lock test test-slow pipeline-ci demo lint bench clean help profile train-sim-tiny train-nav-tiny sim2real push pull

help:  ## list targets
	@grep -E '^[a-z-]+:.*##' $(MAKEFILE_LIST) | sed 's/:.*## /\t/'

setup: $(STAMP)  ## create .venv: torch 2.13.0 CPU first, then the four packages (editable)

$(STAMP): $(SETUP_INPUTS)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade "pip>=24"
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q $(addprefix -e ,$(PACKAGES)) -r requirements-dev.txt -r requirements-pipeline.txt $(if $(LOCKED),-c requirements.lock)
	$(PY) -c "import importlib.util as u, sys; sys.exit(u.find_spec('torchvision') is not None)" \
	  || (echo "torchvision got installed: it breaks transformers on this CPU stack" && exit 1)
	touch $(STAMP)

lock:  ## re-pin requirements.lock from the current .venv (`make setup LOCKED=1` installs exactly those)
	$(PIP) freeze --exclude-editable | grep -v '^-e\|^image2sim' > requirements.lock

test: setup  ## fast test suite (CPU, a few minutes)
	$(PY) -m pytest -q -m "not slow" --durations=15

pipeline-ci: setup  ## the whole dvc pipeline end to end on the `ci` profile, with its checks
	bash scripts/ci_pipeline.sh

test-slow: setup  ## slow tests only
	$(PY) -m pytest -q -m slow --durations=15

demo: setup  ## the main job: `dvc repro` on the active profile (params.yaml), then a summary
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" bash scripts/demo.sh

sim2real: setup  ## train in neural simulators, evaluate in exact held-out houses + scaling curve (pipelines/sim2real, <= 60 min)
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/dvc repro pipelines/sim2real/dvc.yaml
	@cat reports/sim2real.md

# DVC remote for the pipelines' outputs: `local` (.dvc/config) is a directory beside the checkout,
# ../image2sim-dvc-store. DVC_STORE=<dir or URL> points it elsewhere on this machine (written to
# .dvc/config.local, not committed); DVC_REMOTE=<name> picks another configured remote.
DVC_REMOTE ?= local
DVC_STORE ?=
DVC_STORE_SET = $(if $(DVC_STORE),$(VENV)/bin/dvc remote modify --local $(DVC_REMOTE) url "$(if $(findstring ://,$(DVC_STORE)),$(DVC_STORE),$(abspath $(DVC_STORE)))" &&)
push: setup  ## upload the cached outputs of both pipelines to the DVC remote (default ../image2sim-dvc-store)
	$(DVC_STORE_SET) $(VENV)/bin/dvc push -r $(DVC_REMOTE)

pull: setup  ## fetch the pipelines' outputs from the DVC remote into the workspace (then `dvc status` is clean)
	$(DVC_STORE_SET) $(VENV)/bin/dvc pull -r $(DVC_REMOTE)

bench: setup  ## run the benchmarks in benchmarks/ (JSON + Markdown into reports/)
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

RENDERER_DATA ?= $(wildcard ../shared/data/hm3d_360/00000-kfPV7w3FaU5)
# Real captures train with the depth part of the pixel term (configs/renderer/tiny_real.yaml): see its header.
RENDERER_CONFIG ?= $(if $(RENDERER_DATA),configs/renderer/tiny_real.yaml,tiny)
# The HM3D sample is a dense capture (76 training panoramas, almost no holes); training on its sparse
# version (every 4th training frame builds the Gaussians) teaches the renderer to fill holes and scores
# as well on the dense protocol (reports/renderer_tiny.md). 1 = dense.
RENDERER_SOURCE_EVERY ?= $(if $(RENDERER_DATA),4,1)
train-sim-tiny: setup  ## train the tiny pixel-flow renderer on CPU (HM3D sample if present, else procedural rooms)
	$(VENV)/bin/image2sim sim train --config $(RENDERER_CONFIG) --out outputs/renderer-tiny \
	  --source-every $(RENDERER_SOURCE_EVERY) $(addprefix --data ,$(RENDERER_DATA))

NAV_TINY ?= outputs/nav-tiny
NAV_SHARDS = $$(for d in $(NAV_TINY)/engine/scenes/*/shard; do printf -- '--shard %s ' $$d; done)
train-nav-tiny: setup  ## Image2Nav on CPU: data-engine episodes on procedural scenes, BC, online DAgger, vs baselines
	$(VENV)/bin/image2sim data synth --out $(NAV_TINY)/synth --scenes 4 --preset tiny --seed 0 --noise none --overwrite
	$(VENV)/bin/image2sim data episodes --scenes $(NAV_TINY)/synth --out $(NAV_TINY)/engine --per-scene 16 \
	  --obs-height 64 --executor local --render procedural
	$(VENV)/bin/image2sim nav train --stage bc --config configs/navpolicy/tiny-dagger.yaml $(NAV_SHARDS) \
	  --out $(NAV_TINY)/bc --threads 1
	$(VENV)/bin/image2sim nav train --stage dagger --config configs/navpolicy/tiny-dagger.yaml $(NAV_SHARDS) \
	  --init $(NAV_TINY)/bc/export --out $(NAV_TINY)/dagger --scenes 8 --tasks-per-scene 40 --threads 1
	$(VENV)/bin/image2sim nav compare --config configs/navpolicy/tiny-dagger.yaml --model $(NAV_TINY)/bc/export \
	  --agents image2nav --episodes-per-scene 30 --out $(NAV_TINY)/compare-bc.json
	$(VENV)/bin/image2sim nav compare --config configs/navpolicy/tiny-dagger.yaml --model $(NAV_TINY)/dagger/export \
	  --episodes-per-scene 30 --out $(NAV_TINY)/compare.json
	$(VENV)/bin/image2sim nav act --config configs/navpolicy/tiny-dagger.yaml --model $(NAV_TINY)/dagger/export \
	  --out $(NAV_TINY)/act

lint: setup
	$(VENV)/bin/ruff check packages tests benchmarks

clean:
	rm -rf $(VENV) .pytest_cache outputs

PROFILE ?= demo
profile:  ## switch the pipeline profile: make profile PROFILE=demo|ci|paper
	cp configs/profiles/$(PROFILE).yaml params.yaml
	@echo "params.yaml <- configs/profiles/$(PROFILE).yaml"
