# cloudpose: every target is a thin call of the CLI (`cloudpose --help`); `make help` lists them.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
CLI := $(VENV)/bin/cloudpose
TORCH_SPEC ?= torch==2.13.0
PRESET ?= cpu
SEEDS ?= 3
VARIANT ?= shared-0
SEED ?= 1

.DEFAULT_GOAL := help
.PHONY: help setup install demo test test-fast lint format variants

help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  \033[36m%-18s\033[0m %s\n", $$1, $$2}'

setup: install demo ## fresh machine: system libraries, virtualenv, package; then the main job on the smoke preset

install: ## system libraries (libusb for Open3D, tcmalloc), .venv, the package in editable mode with dev tools
	@need=""; for lib in libusb-1.0.so.0 libtcmalloc_minimal.so.4; do \
	  ldconfig -p | grep -q "$$lib" || need="$$need $$lib"; done; \
	if [ -n "$$need" ]; then \
	  echo "installing system libraries for:$$need"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 libtcmalloc-minimal4 >/dev/null \
	  || echo "warning: could not install libusb-1.0-0/libtcmalloc-minimal4; Open3D needs libusb (tcmalloc is optional)"; fi
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e '.[dev]'

demo: ## the main job on the smoke preset: synth -> prepare -> train -> evaluate
	$(CLI) run --variant $(VARIANT) --preset smoke --seed $(SEED)

test: ## the test suite (what .ci/run runs)
	$(PY) -m pytest -q -n 2 --durations=15

test-fast: ## the tests without the slow ones
	$(PY) -m pytest -q -n 2 -m "not slow"

lint: ## ruff check and format check
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format: ## ruff fix and format
	$(VENV)/bin/ruff check --fix . && $(VENV)/bin/ruff format .

variants: ## print the variant registry with parameter counts
	$(CLI) variants
