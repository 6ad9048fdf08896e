# cosim5g: `make help` lists the targets.
SHELL := /bin/bash
# Python 3.11: python3.11 where it exists (python3 may be another version), else python3.
PYTHON ?= $(shell command -v python3.11 >/dev/null 2>&1 && echo python3.11 || echo python3)
VENV ?= .venv
BIN := $(VENV)/bin
SCENARIO ?= co_design
SCENARIO_FILE := configs/scenarios/$(SCENARIO).yaml
RESULTS ?= results/runs
export MUJOCO_GL ?= egl

.DEFAULT_GOAL := help
# Found when a recipe runs, not when make starts: `setup` may install it on the way.
COMPOSE = $$(docker compose version >/dev/null 2>&1 && echo "docker compose" || echo docker-compose)
# Whether a Docker daemon answers this user: the docker tests then need the images.
DOCKER_UP := $(shell docker info >/dev/null 2>&1 && echo yes)
API ?= http://127.0.0.1:8080
# Compose needs the docker socket's group (the coordinator starts run containers) and runs the
# coordinator as the invoking user so that results/ stays theirs -- never as root: a root caller's
# results/ is handed to the image's user (uid 10001).
PLATFORM_UID := $$(u=$$(id -u); [ $$u = 0 ] && echo 10001 || echo $$u)
PLATFORM_GID := $$(u=$$(id -u); [ $$u = 0 ] && echo 10001 || id -g)
COMPOSE_ENV := DOCKER_GID=$$(stat -c %g /var/run/docker.sock) COSIM5G_UID=$(PLATFORM_UID) COSIM5G_GID=$(PLATFORM_GID)

.PHONY: help setup scenario-check dashboards install run smoke test test-unit test-integration lint bench bench-cluster load bench-docker images up down \
	reproduce reproduce-quick reproduce-codesign reproduce-family reproduce-overload reproduce-load-feature reproduce-shared-edge reproduce-sensitivity reproduce-factory soak chaos native \
	calibrate measure-frames train-perception train-policy policy-network install-train clean

help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  \033[36m%-18s\033[0m %s\n", $$1, $$2}'

# The interpreter is found again after host_setup (which may have just installed python3.11),
# unless PYTHON was given.
$(BIN)/cosim5g: pyproject.toml
	PYTHON=$(PYTHON) bash images/host_setup.sh python egl
	py=$(PYTHON); [ "$(origin PYTHON)" = file ] && command -v python3.11 >/dev/null && py=python3.11; \
	  $$py -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[api,plots,dev,ray]'
	@touch $@

setup: ## check the host (Python 3.11 venv, Docker + compose, EGL/Mesa); as root install what is missing, else print the command
	PYTHON=$(PYTHON) bash images/host_setup.sh

install: $(BIN)/cosim5g ## create .venv and install the project with its test tools

# The NR cell compiled with mypyc (fabric.native): the same code about 1.4 times as fast, and the
# physics stepper's C thread. It is used only while its sources are unchanged, so every target that
# runs the simulator rebuilds it first (a no-op when up to date); without a C compiler netsim runs
# as pure Python and physics steps in a Python thread.
native: $(BIN)/cosim5g ## compile the NR cell's modules (mypyc) and the physics stepper (C) into build/native (used while their sources are unchanged)
	-$(BIN)/python tools/native.py build

run: scenario-check $(BIN)/cosim5g native ## run SCENARIO (default co_design) in the process runtime, print KPIs
	$(BIN)/cosim5g run $(SCENARIO_FILE) --results $(RESULTS)

smoke: $(BIN)/cosim5g native ## run the 2-loop smoke scenario in the process runtime
	$(BIN)/cosim5g run configs/scenarios/smoke.yaml --results $(RESULTS)

PACKAGES := scenario fabric wire domain services netsim coordinator experiments training interfaces

lint: $(BIN)/cosim5g ## ruff over the code, and the layer contracts (import-linter, see pyproject.toml)
	$(BIN)/ruff check $(PACKAGES) benchmarks tools tests
	$(BIN)/lint-imports

# With a Docker daemon the images are built first, so that the docker tests run; a build that
# cannot be done here (no base image, no registry, not root) leaves them to skip, saying why,
# and the other tests run.
test: $(BIN)/cosim5g native ## lint (ruff + layer contracts), mypy, then every test (with a Docker daemon, the images are built first and the docker tests run)
	$(if $(DOCKER_UP),-$(MAKE) --no-print-directory images)
	$(BIN)/ruff check $(PACKAGES) benchmarks tools tests
	$(BIN)/lint-imports
	$(BIN)/mypy $(PACKAGES) benchmarks tools
	$(BIN)/pytest -q $(PYTEST_ARGS)

test-unit: $(BIN)/cosim5g native ## fast unit tests only (in-memory bus)
	$(BIN)/pytest -q tests/unit

test-integration: $(BIN)/cosim5g native ## runs over real zenoh and real processes
	$(BIN)/pytest -q -m integration

bench: $(BIN)/cosim5g native ## benchmarks: conductor windows/s, smoke real-time factor, speed of 32-loop runs, of the 360-loop 18-gNB factory (5 s: the first tasks end) and of netsim (results/bench/)
	$(BIN)/python -m benchmarks.platform_bench
	$(BIN)/python -m benchmarks.speed

bench-cluster: $(BIN)/cosim5g native ## the factory in 1, 2 and 4 netsim partitions, in processes and on 1, 2 and 4 local Ray nodes where the cores allow: speed, scaling efficiency, window protocol share (results/bench/cluster.md)
	$(BIN)/python -m benchmarks.cluster

soak: $(BIN)/cosim5g native ## 100 smoke runs in one coordinator + 20 in containers (RUNS, DOCKER_RUNS): leftovers, RSS, fds (results/bench/)
	$(BIN)/python -m benchmarks.reliability soak --runs $(or $(RUNS),100) --docker-runs $(or $(DOCKER_RUNS),20)

load: $(BIN)/cosim5g native ## load test of the REST API: REQUESTS (1000) mixed requests from CLIENTS (8) against one coordinator: p99, RSS, 5xx, queue limit, nothing lost (results/bench/)
	$(BIN)/python -m benchmarks.api_load --requests $(or $(REQUESTS),1000) --clients $(or $(CLIENTS),8)

chaos: $(BIN)/cosim5g native ## 30 runs, both runtimes, each with a random fault (kill/stop a federate, kill the coordinator, OOM in docker): end states, leftovers
	$(BIN)/python -m benchmarks.reliability chaos --runs $(or $(RUNS),30) --runtime $(or $(RUNTIME),both)

# Points of the study's sweeps run side by side, one per core: they have no detailed loop (every
# job duration is drawn, `model` timing), so sharing the host changes no result, only the wall time.
JOBS ?= $(shell getconf _NPROCESSORS_ONLN 2>/dev/null || echo 1)
reproduce: $(BIN)/cosim5g native ## the study's sweep (loops 2..36 x none/heuristic x 3 seeds, 60 s points): capacity, Fig. 4-6, report
	$(BIN)/cosim5g sweep configs/sweeps/reproduce.yaml --jobs $(JOBS)

reproduce-quick: $(BIN)/cosim5g native ## the same, short: loops 4..36 step 4, one seed, 15 s points (results/sweeps/)
	$(BIN)/cosim5g sweep configs/sweeps/quick.yaml --jobs $(JOBS)

reproduce-codesign: $(BIN)/cosim5g native ## where co-design's capacity comes from: none/heuristic/learned (app, lower) + ablations, default cell and 3 family cells
	$(BIN)/cosim5g sweep configs/sweeps/codesign.yaml --jobs $(JOBS)
	$(BIN)/cosim5g sweep configs/sweeps/codesign_family.yaml --jobs $(JOBS)

reproduce-family: $(BIN)/cosim5g native ## co-design on 13 work cells of the training family x policy x floor x 3 seeds: capacity, gain over PDP 1 and the invariant per cell (hours on 2 cores)
	$(BIN)/cosim5g sweep configs/sweeps/family.yaml --jobs $(JOBS)

reproduce-overload: $(BIN)/cosim5g native ## none/heuristic/learned from below saturation to several times the radio cell's capacity: success, injected vs delivered traffic
	$(BIN)/cosim5g sweep configs/sweeps/overload.yaml --jobs $(JOBS)

reproduce-load-feature: $(BIN)/cosim5g native ## the learned policy with its load input live or frozen at an idle cell's, under the Edge's bounds and under the floor alone
	$(BIN)/cosim5g sweep configs/sweeps/load_feature.yaml --jobs $(JOBS)

reproduce-shared-edge: $(BIN)/cosim5g native ## none/heuristic/learned on one Edge CPU shared by every loop, estimating every frame or each loop's newest: capacity where the Edge saturates
	$(BIN)/cosim5g sweep configs/sweeps/shared_edge.yaml --jobs $(JOBS)

reproduce-factory: $(BIN)/cosim5g native ## InF-SL hall with 1, 4, 18 gNBs x none/heuristic/learned x 1..30 loops per gNB: capacity per layout and per gNB, SINR CDFs (about 12 min on 2 cores)
	$(BIN)/cosim5g sweep configs/sweeps/factory_gnbs.yaml --jobs $(JOBS)

reproduce-sensitivity: $(BIN)/cosim5g native ## task success vs a fixed extra uplink latency (0-200 ms) x frame loss (0-90%), three work cells, abstract then detailed loops
	$(BIN)/cosim5g sweep configs/sweeps/sensitivity.yaml --jobs $(JOBS)
	$(BIN)/cosim5g sweep configs/sweeps/sensitivity_detailed.yaml --jobs 1

images: setup $(BIN)/cosim5g native ## build the runtime and Prometheus images without a registry (see docs/docker.md)
	PYTHON=$(PYTHON) bash images/build.sh

TOKEN_FILE := $(CURDIR)/results/auth/api-token
TOKEN_AT = $$([ -n "$$COSIM5G_TOKEN" ] && echo 'the value of COSIM5G_TOKEN' || echo '$(TOKEN_FILE) (mode 0600)')
scenario-check:
	@[ -f $(SCENARIO_FILE) ] || { echo "SCENARIO=$(SCENARIO): no $(SCENARIO_FILE); shipped: $$(ls configs/scenarios | sed 's/\.yaml$$//' | tr '\n' ' ')" >&2; exit 2; }

up: scenario-check images ## start the platform (coordinator API + Prometheus) and run SCENARIO in containers
	mkdir -p results/runs
	chown -R $(PLATFORM_UID):$(PLATFORM_GID) results
	$(COMPOSE_ENV) $(COMPOSE) up -d
	@echo "API token: $(TOKEN_AT); the coordinator writes the file at its first start, cosim5g submit reads it"
	$(BIN)/cosim5g submit $(SCENARIO) --set runtime=docker --follow --api $(API)
	@echo "platform still up: API $(API) (bearer token: $(TOKEN_AT); a browser: $(API)/login?token=<token>), Prometheus http://127.0.0.1:9090; 'make down' removes it"

GRAFANA_IMAGE := grafana/grafana-oss:11.3.1
dashboards: ## start Grafana (http://127.0.0.1:3000) beside the platform `make up` started; its image must be in the local cache
	@docker image inspect $(GRAFANA_IMAGE) >/dev/null 2>&1 || { echo "no $(GRAFANA_IMAGE) in the local image cache: run 'docker pull $(GRAFANA_IMAGE)' where a registry answers (or 'docker load' it), then 'make dashboards'" >&2; exit 2; }
	$(COMPOSE_ENV) $(COMPOSE) --profile dashboards up -d grafana
	@echo "dashboards: http://127.0.0.1:3000 (overview, network, control, compute); Prometheus http://127.0.0.1:9090"

down: ## stop the platform and remove its containers, networks and volumes (and leftovers of runs)
	-$(COMPOSE_ENV) $(COMPOSE) down -v --remove-orphans
	-$(BIN)/python -c "from coordinator.docker_runs import reap_dead_runs; from coordinator.runtime_docker import docker_client; reap_dead_runs(docker_client())"

calibrate: images native ## real workloads at cpus 1/0.5/0.25, process + docker: cpu-mode and wall vs ideal, 95% CIs (results/bench/)
	$(BIN)/cosim5g calibrate --runtime both --rounds $(or $(ROUNDS),6) --jobs $(or $(CAL_JOBS),6)

bench-docker: images native ## make bench plus runs in containers: docker/process speed ratios
	$(BIN)/python -m benchmarks.platform_bench --docker
	$(BIN)/python -m benchmarks.speed --docker

install-train: $(BIN)/cosim5g ## add torch, onnx, gymnasium, stable-baselines3 to .venv (several GB: PyPI's torch brings CUDA libraries)
	$(BIN)/pip install --quiet -e '.[api,plots,dev,ray,train]'

train-perception: install-train ## render the pose data set, train the Edge pose network (CPU), export pose.onnx, re-measure
	$(BIN)/python tools/train_perception.py --regenerate
	$(BIN)/python tools/perception_dataset.py --split test --episodes 10
	$(BIN)/python -m benchmarks.perception_accuracy --record
	$(BIN)/python tools/measure_frames.py

# The full path trains one PPO policy per lambda (two at a time, one core each, about 15 min on
# two cores), writes results/policy/pareto.md and ships the chosen one; QUICK=1 trains, exports,
# checks and evaluates one policy on a tiny budget into a temporary directory (about a minute; no
# lambda sweep, no hall runs, nothing shipped).
train-policy: install-train ## co-design policy: PPO per lambda, Pareto table, runs in the overload hall, ship domain/models/policy.onnx (QUICK=1: 1-min check)
	$(if $(QUICK),$(BIN)/python tools/train_policy.py --quick,nice -n 19 $(BIN)/python tools/policy_sweep.py --ship)

policy-network: $(BIN)/cosim5g ## re-measure the policy environment's network table on the NR cell (training/policy/data/)
	$(BIN)/python benchmarks/policy_network_table.py

measure-frames: $(BIN)/cosim5g ## re-measure frame sizes and estimator error for the abstract loops
	$(BIN)/python tools/measure_frames.py

clean: ## remove results and caches (keeps .venv)
	rm -rf results .pytest_cache .ruff_cache .mypy_cache build/native
