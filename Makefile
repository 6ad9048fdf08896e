# cosim5g: `make help` lists the targets.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
SCENARIO ?= co_design
SCENARIO_FILE := configs/scenarios/$(SCENARIO).yaml
RESULTS ?= results/runs
export MUJOCO_GL ?= egl

.DEFAULT_GOAL := help
.PHONY: help install run smoke test test-unit test-integration lint bench measure-frames clean

help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  \033[36m%-18s\033[0m %s\n", $$1, $$2}'

$(BIN)/cosim5g: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[api,plots,dev]'
	@touch $@

install: $(BIN)/cosim5g ## create .venv and install the project with its test tools

run: $(BIN)/cosim5g ## run SCENARIO (default co_design) in the process runtime, print KPIs
	$(BIN)/cosim5g run $(SCENARIO_FILE) --results $(RESULTS)

smoke: $(BIN)/cosim5g ## run the 2-loop smoke scenario in the process runtime
	$(BIN)/cosim5g run configs/scenarios/smoke.yaml --results $(RESULTS)

lint: $(BIN)/cosim5g ## ruff over the code
	$(BIN)/ruff check coordinator services netsim benchmarks tests

test: $(BIN)/cosim5g ## lint, then every test (docker tests run when a Docker daemon answers)
	$(BIN)/ruff check coordinator services netsim benchmarks tests
	$(BIN)/pytest -q $(PYTEST_ARGS)

test-unit: $(BIN)/cosim5g ## fast unit tests only (in-memory bus)
	$(BIN)/pytest -q tests/unit

test-integration: $(BIN)/cosim5g ## runs over real zenoh and real processes
	$(BIN)/pytest -q -m integration

bench: $(BIN)/cosim5g ## benchmarks: conductor windows/s, smoke real-time factor (results/bench/)
	$(BIN)/python -m benchmarks.platform_bench

measure-frames: $(BIN)/cosim5g ## re-measure frame sizes and estimator error for the abstract loops
	$(BIN)/python -m services.camera.measure

clean: ## remove results and caches (keeps .venv)
	rm -rf results .pytest_cache .ruff_cache .mypy_cache
