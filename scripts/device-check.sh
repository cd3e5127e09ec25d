#!/bin/sh
# The GPU check (orchestrator/bench/device.py) on a machine with PyTorch (CUDA) and NumPy but no network:
# installs the wheels `make device-wheels` put in .device/wheels (carried with the tree) into .device/site,
# then runs the check. Arguments go to `python -m orchestrator.bench device` (e.g. --json --out FILE).
set -e
cd "$(dirname "$0")/.."
"${PYTHON:-python3}" -m pip install --quiet --no-index --no-deps --target .device/site .device/wheels/*.whl
PYTHONPATH=".device/site:." "${PYTHON:-python3}" -m orchestrator.bench device "$@"
