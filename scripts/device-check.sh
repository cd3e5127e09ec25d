#!/bin/sh
# The GPU check (orchestrator/bench/device.py) on a machine with PyTorch (CUDA) and NumPy but no network:
# installs the wheels `make device-wheels` put in .device/wheels (carried with the tree) into .device/site,
# then runs the check. Arguments go to `python -m orchestrator.bench device` (e.g. --json --out FILE); without any,
# `--devices cuda --seconds 1`, which is meant to stay inside one call of at most 8 minutes (the CPU's rows take a
# call of their own: `--devices cpu --seconds 1`). Not yet run on a GPU at these settings.
set -e
cd "$(dirname "$0")/.."
"${PYTHON:-python3}" -m pip install --quiet --no-index --no-deps --target .device/site .device/wheels/*.whl
[ $# -gt 0 ] || set -- --devices cuda --seconds 1
PYTHONPATH=".device/site:." "${PYTHON:-python3}" -m orchestrator.bench device "$@"
