# cloudpose: every target is a thin call of the CLI (`cloudpose --help`); `make help` lists them.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
CLI := $(VENV)/bin/cloudpose
TORCH_SPEC ?= torch==2.13.0
PRESET ?= cpu-online
SEEDS ?= 3
VARIANT ?= shared-0
SEED ?= 1

.DEFAULT_GOAL := help
.PHONY: help setup install demo showcase test test-all test-slow lint format variants

help: ## list the targets
	@if [ -t 1 ]; then c='\033[36m'; r='\033[0m'; else c=; r=; fi; \
	grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' -v c="$$c" -v r="$$r" '{printf "  %s%-18s%s %s\n", c, $$1, r, $$2}'

setup: install demo showcase ## fresh machine: system libraries, virtualenv, package; the pipeline's plumbing check; the shipped network on real and synthetic frames

install: ## system libraries (libusb for Open3D, tcmalloc), .venv, the package in editable mode with dev tools and Ray
	@need=""; for lib in libusb-1.0.so.0 libtcmalloc_minimal.so.4; do \
	  ldconfig -p | grep -q "$$lib" || need="$$need $$lib"; done; \
	if [ -n "$$need" ]; then \
	  echo "installing system libraries for:$$need"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 libtcmalloc-minimal4 >/dev/null \
	  || echo "warning: could not install libusb-1.0-0/libtcmalloc-minimal4; Open3D needs libusb (tcmalloc is optional)"; fi
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install "$(TORCH_SPEC)"
	$(PY) -m pip install -c constraints.txt -e '.[dev,cluster]'

demo: ## (DRY=1: its plan) plumbing check of the main job on the smoke preset: synth -> prepare -> train (seconds) -> evaluate; its numbers are near zero by design
	$(CLI) run --variant $(VARIANT) --preset smoke --seed $(SEED) $(if $(DRY),--dry-run)

showcase: ## the shipped network (shared-0 of the gpu preset) beside FPFH + RANSAC on the 61 real frames and 40 synthetic test frames, with the paper's ICP and the wide refinement, + an overlay picture (no training)
	$(CLI) showcase --out runs/showcase

test: ## the tests without the slow-marked ones (~4 min on 2 cores): the everyday loop
	$(PY) -m pytest -q -n 2 -m "not slow" --durations=10

test-all: ## every test, the slow-marked ones included (what .ci/run runs; 15-26 min on 2 cores, by CPU)
	$(PY) -m pytest -q -n 2 --durations=15

test-slow: ## only the slow-marked tests (multi-class recipe, Ray with a killed node, resumes, torchrun, ...)
	$(PY) -m pytest -q -n 2 -m slow --durations=15

lint: ## ruff check and format check
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format: ## ruff fix and format
	$(VENV)/bin/ruff check --fix . && $(VENV)/bin/ruff format .

variants: ## print the variant registry with parameter counts
	$(CLI) variants

# --- ablation suite and reports (cloudpose ablate / report / occlusion-report) ---------------
MLFLOW_URI ?= $(MLFLOW_TRACKING_URI)
MLFLOW_PORT ?= 5000
GROUP ?=
EXECUTOR ?= local
MLFLOW_HOST ?= 127.0.0.1
# DRY=1: print the plan of a training target (what the store holds, what would train, how long)
# and stop. FRESH=1: train every run anew into ./mlflow.db instead of reusing the committed sweep
# (stores/PRESET/, unpacked once from reports/PRESET/mlflow-store).
SWEEP_FLAGS = $(if $(DRY),--dry-run) $(if $(FRESH),--fresh)
.PHONY: headline-claims ablations-resolve ablation-shared ablation-rotation ablation-loss ablation-symmetry ablations ablation-masks baselines occlusion-report occlusion-runs real-report tables mlflow-ui mlflow-server

ablation-shared: ## shared-layers group: train+evaluate every variant x SEEDS on PRESET, reusing the committed runs (DRY=1: the plan only; FRESH=1: retrain all), then its reports
	$(CLI) ablate --group shared --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) $(SWEEP_FLAGS)

ablation-rotation: ## rotation-representation group (axis-angle, quaternion, 6D) x SEEDS on PRESET, then its reports
	$(CLI) ablate --group rotation --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) $(SWEEP_FLAGS)

ablation-loss: ## rotation-loss group (geodesic, L2) x SEEDS on PRESET, then its reports
	$(CLI) ablate --group loss --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) $(SWEEP_FLAGS)

ablation-symmetry: ## rotation loss modulo symmetry vs the plain geodesic x SEEDS on PRESET, then its reports
	$(CLI) ablate --group symmetry --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) $(SWEEP_FLAGS)

ablations: ablation-shared ablation-rotation ablation-loss ablation-symmetry ## all four ablation groups (EXECUTOR=ray: a Ray task per run, cluster RAY_ADDRESS)

MAX_SEEDS ?= 10
ablations-resolve: ## every group x SEEDS, then more seeds (up to MAX_SEEDS) for the variants of each undecided claim; then the reports
	for g in shared rotation loss symmetry; do $(CLI) ablate --group $$g --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) --until-resolved $(MAX_SEEDS) $(SWEEP_FLAGS) || exit 1; done

AGAINST ?= cpu-online
headline-claims: ## the paper's headline claims on PRESET (e.g. PRESET=cpu-online-4x): shared-0, shared-all, quaternion, l2, geodesic-plain x SEEDS (finished runs skipped), then claims.md with AGAINST's verdicts beside
	$(CLI) ablate --group shared --only shared-0 --only shared-all --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) $(SWEEP_FLAGS)
	for g in rotation:quaternion loss:l2 symmetry:geodesic-plain; do $(CLI) ablate --group $${g%%:*} --only shared-0 --only $${g#*:} --preset $(PRESET) --seeds $(SEEDS) --executor $(EXECUTOR) $(SWEEP_FLAGS) || exit 1; done
	$(if $(DRY),@echo "then: claims.md of $(PRESET) with $(AGAINST)'s verdicts beside",$(CLI) report --preset $(PRESET) --against $(AGAINST))

ablation-masks: ## segmentation quality: shared-0 x SEEDS (trained on ground truth if missing) under gt and degraded-mild/medium/strong test masks, with and without ICP; table and occlusion plot
	$(CLI) ablate-masks --preset $(PRESET) --seeds $(SEEDS) $(SWEEP_FLAGS)

baselines: ## classical baselines on PRESET's test set, with and without ICP: FPFH + RANSAC (SEEDS seeds), point-pair features (deterministic: seed 1); runs the store holds (the committed sweep's included) are skipped (FRESH=1: into ./mlflow.db)
	@echo "plan: baselines on the $(PRESET) test set, without and with ICP: FPFH + RANSAC seeds 1-$(SEEDS), point-pair features once; a run logged before (the committed sweep's included, unless FRESH=1) is shown, not computed again"
	$(if $(DRY),,for s in $$(seq 1 $(SEEDS)); do $(CLI) baseline --method fpfh --preset $(PRESET) --seed $$s $(if $(FRESH),--fresh) || exit 1; done)
	$(if $(DRY),,$(CLI) baseline --method ppf --preset $(PRESET) $(if $(PPF_LIMIT),--limit $(PPF_LIMIT)) $(if $(FRESH),--fresh))

occlusion-report: ## occlusion plot of shared-0 without/with ICP from existing runs only (a missing run: names it and fails; GROUP=... adds a group's variants)
	$(CLI) occlusion-report --preset $(PRESET) --seeds $(SEEDS) $(if $(GROUP),--group $(GROUP))

occlusion-runs: ## train + evaluate the runs occlusion-report needs that are missing (prints the plan first), then the plot
	$(CLI) occlusion-report --preset $(PRESET) --seeds $(SEEDS) $(if $(GROUP),--group $(GROUP)) --train-missing $(if $(DRY),--dry-run)

real-report: ## the 61 real development frames per video and pooled: shared-0 (every seed found) and both baselines, without/with ICP -> reports/PRESET/real_frames.md (reads runs only)
	$(CLI) real-report --preset $(PRESET) --seeds $(SEEDS)

.PHONY: compare
compare: ## the shipped network, FPFH + RANSAC, point-pair features and no estimate on the same segments, refined alike: the 61 real frames, or DATA=ROOT [FRAMES=all] -> runs/compare/ (~20 min on 2 cores)
	$(CLI) compare $(if $(DATA),--data $(DATA) $(if $(FRAMES),--frames $(FRAMES)))

tables: ## every report of PRESET into reports/PRESET/ from existing MLflow runs (no training)
	$(CLI) report --all --preset $(PRESET)

.PHONY: renderer-vs-real
renderer-vs-real: ## synthetic frames (generator versions 1 and 2) against the real frames in tests/data -> reports/renderer_vs_real.md
	$(CLI) synth --compare-real tests/data/ycb_real --compare-real tests/data/demo_no_gt --compare-frames 20 --report reports/renderer_vs_real.md

mlflow-server: ## MLflow tracking server for several machines on MLFLOW_HOST:MLFLOW_PORT (127.0.0.1:5000): SQLite ./mlflow-server/ or MLFLOW_BACKEND, artifacts served
	$(CLI) mlflow-server --host $(MLFLOW_HOST) --port $(MLFLOW_PORT) $(if $(MLFLOW_BACKEND),--backend $(MLFLOW_BACKEND))

mlflow-ui: ## MLflow UI on http://127.0.0.1 (MLFLOW_PORT=5000) over the committed sweep and the runs added to it (MLFLOW_URI=sqlite:///mlflow.db: your own store); prints each group's saved view
	$(CLI) mlflow-ui $(if $(MLFLOW_URI),--backend $(MLFLOW_URI)) --host 127.0.0.1 --port $(MLFLOW_PORT)

# --- benchmarks ---------------------------------------------------------------------
.PHONY: bench

bench: ## the benchmark suite -> reports/benchmarks.md and reports/benchmarks.json
	$(PY) -m benchmarks.run_all
