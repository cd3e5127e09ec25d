# One-command entry points. `make setup` creates .venv with the CPU build of torch,
# then the project and its pinned dependencies (constraints.txt).
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
TORCH ?= torch==2.13.0

.PHONY: setup samples system-packages run test test-all bench device-wheels device-warp gpu-smoke lint

# Debian packages the project uses beside Python: PostgreSQL's server (MLflow's backend store in
# `make cluster-up`) and the GL libraries of MuJoCo's offscreen renderer (evaluation videos:
# MUJOCO_GL=egl or osmesa), docker-compose to check docker/compose.yaml (no daemon needed), and a C++
# compiler for torch.compile's CPU kernels (runtime.learner_compile, bench learners --compile).
# Needs root; elsewhere it prints the command to run.
SYSTEM_PACKAGES := postgresql libosmesa6 libegl1 libgl1 libgles2 docker-compose g++
system-packages:
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(SYSTEM_PACKAGES); \
	else echo "install as root: apt-get install $(SYSTEM_PACKAGES)"; fi

setup:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install $(TORCH)
	$(BIN)/pip install -c constraints.txt -e '.[dev,warp]'
	$(MAKE) samples

# Third-party BVH files the import tests read (from bvhtoolbox's and bvhtools' sdists on PyPI; tests/samples.py).
samples:
	$(BIN)/python -m tests.samples

# The main job: the default ControlVAE run (see README).
run:
	$(BIN)/python -m orchestrator

test:
	$(BIN)/python -m pytest -q

bench:
	$(BIN)/python -m orchestrator.bench sim --json --out bench-results/sim.json
	$(BIN)/python -m orchestrator.bench learners --json --out bench-results/learners.json
	$(BIN)/python -m orchestrator.bench pipeline --json --out bench-results/pipeline.json

# The GPU check's wheels (orchestrator/bench/device.py): MuJoCo and what `import mujoco` needs, for the GPU
# machine's Python (no network there); `sh scripts/device-check.sh` installs and runs them there.
DEVICE_PY ?= 3.12
device-wheels:
	$(BIN)/pip download --no-deps --only-binary=:all: --implementation cp --python-version $(DEVICE_PY) \
		--platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 -d .device/wheels \
		mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw==2.11.0 pyopengl==3.1.10

# The MuJoCo Warp checks' packages: the GPU smoke's (.device/smoke; docs/warp.md, "On a GPU").
device-warp:
	PYTHON=$(BIN)/python sh scripts/device-warp.sh prepare

# What the GPU smoke carries to the GPU machine (.device/smoke: its packages for Python 3.12, packed; the clips).
gpu-smoke:
	PYTHON=$(BIN)/python sh scripts/gpu-smoke.sh prepare

lint:
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# The cluster topology on this machine, no Docker: a Ray head and a Ray node (token authentication on),
# PostgreSQL and an MLflow server on it (MLflow's basic-auth app: every request needs a user and password);
# addresses in $(CLUSTER_DIR)/cluster.json, passwords in 0600 files beside it. `cluster-down` stops the
# services and deletes no data (the database, artifacts and jobs' directories stay). See docs/cluster.md.
CLUSTER_DIR ?= .cluster
.PHONY: cluster-up cluster-down
cluster-up:
	$(BIN)/python -m orchestrator.cluster up --state-dir $(CLUSTER_DIR)

cluster-down:
	$(BIN)/python -m orchestrator.cluster down --state-dir $(CLUSTER_DIR)
