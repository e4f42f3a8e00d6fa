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
STAMP       := $(VENV)/.installed

.PHONY: install demo test test-slow test-all bench clean

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	bash .ci/system-deps llvm
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]" "$(TORCH_SPEC)"
	$(BIN)/camo doctor
	touch $(STAMP)

demo: install
	$(BIN)/camo scenes render $(DEMO_SCENE) --out $(DEMO_OUT)/$(DEMO_SCENE)/scene

test: install
	bash .ci/system-deps chromium
	$(BIN)/python -m pytest -q

test-slow: install
	bash .ci/system-deps chromium
	$(BIN)/python -m pytest -q -m slow

test-all: install
	bash .ci/system-deps chromium
	$(BIN)/python -m pytest -q -m "slow or not slow"

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache
