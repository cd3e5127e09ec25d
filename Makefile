# One-command entry points. `make setup` creates .venv with the CPU build of torch,
# then the project and its pinned dependencies (constraints.txt).
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
TORCH ?= torch==2.13.0

.PHONY: setup run test test-all bench lint

setup:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install $(TORCH)
	$(BIN)/pip install -c constraints.txt -e '.[dev]'

# The main job: the default ControlVAE run (see README).
run:
	$(BIN)/python -m orchestrator

test:
	$(BIN)/python -m pytest -q

bench:
	$(BIN)/python -m orchestrator.bench sim --json --out bench-results/sim.json
	$(BIN)/python -m orchestrator.bench learners --json --out bench-results/learners.json
	$(BIN)/python -m orchestrator.bench pipeline --json --out bench-results/pipeline.json

lint:
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
