#!/bin/sh
# The GPU smoke in one call (issue 45): on a GPU machine with PyTorch (CUDA), NumPy and Python 3.12 but no network,
# which takes other packages only as files carried with the working tree (64 MiB a call) and keeps nothing between
# calls. Prints one line per check (PASS, FAIL or SKIP, its seconds, what it saw: scripts/gpu_smoke.py) and exits 1
# when one fails.
#
# Here (network), once:  sh scripts/gpu-smoke.sh prepare      (make gpu-smoke)
#   installs the packages the checks need beside torch and numpy (MuJoCo, Hydra, SciPy and dtw-python, matplotlib:
#   constraints.txt's pins) for Python 3.12 into a folder, drops their tests, packs it as .device/smoke/site.tar.xz
#   (about 49 MB: xz packs them tighter than their wheels, 85 MB), copies the bundled clips beside it, and prints
#   what the call carries.
# There:  sh scripts/gpu-smoke.sh        with carry [".device/smoke"]
#   unpacks it (Python's tarfile, a few seconds) and runs the checks on cuda. warp-lang does not fit (149 MB; its
#   warp.so is 78 MB even xz-compressed): the Warp checks SKIP unless the machine has it (scripts/device-warp.sh
#   carries it in parts over warm calls).
# Here, the dry run:  DRY_RUN=cpu sh scripts/gpu-smoke.sh     the same checks on the CPU and Warp's CPU device,
#   with this checkout's environment (PYTHON, else .venv/bin/python, else python3).
set -e
cd "$(dirname "$0")/.."
DIR=.device/smoke
DEVICE_PY="${DEVICE_PY:-3.12}"
PACKAGES="mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw==2.11.0 PyOpenGL==3.1.10 hydra-core==1.3.8
omegaconf==2.3.1 PyYAML==6.0.3 tqdm==4.70.1 psutil==7.2.2 scipy==1.17.1 dtw-python==1.9.0 matplotlib==3.11.2
contourpy==1.3.3 cycler==0.12.1 fonttools==4.68.0 kiwisolver==1.5.1 pillow==13.0.0 pyparsing==3.3.3
python-dateutil==2.9.0.post0 six==1.17.0"
ANTLR=antlr4-python3-runtime==4.9.3  # hydra's parser runtime: an sdist only, built into a wheel here

prepare() {
    PY="${PYTHON:-.venv/bin/python}"
    work=$(mktemp -d)
    mkdir -p "$work/wheels" "$work/site"
    # shellcheck disable=SC2086
    "$PY" -m pip download --quiet --no-deps --only-binary=:all: --implementation cp --python-version "$DEVICE_PY" \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d "$work/wheels" $PACKAGES
    "$PY" -m pip wheel --quiet --no-deps -w "$work/wheels" "$ANTLR"
    "$PY" - "$work" <<'EOF'
import glob, shutil, sys, zipfile
from pathlib import Path

work = Path(sys.argv[1])
for wheel in sorted(glob.glob(f"{work}/wheels/*.whl")):
    zipfile.ZipFile(wheel).extractall(work / "site")
for tests in [p for p in (work / "site").rglob("tests") if p.is_dir()]:
    shutil.rmtree(tests, ignore_errors=True)
shutil.rmtree(work / "site" / "matplotlib" / "mpl-data" / "sample_data", ignore_errors=True)
EOF
    rm -rf "$DIR" && mkdir -p "$DIR"
    tar -C "$work/site" -cf - . | xz -T0 -9 >"$DIR/site.tar.xz"
    cp -r "$("$PY" -c 'import pybullet_data; print(pybullet_data.getDataPath())')/data/motions" "$DIR/motions"
    rm -rf "$work"
    tree=$(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)
    carried=$(du -cb "$DIR" | tail -1 | cut -f1)
    echo "$DIR: $((carried / 1048576)) MiB, the tree $((tree / 1048576)) MiB; carry [\"$DIR\"]: sh scripts/gpu-smoke.sh"
    if [ $((carried + tree)) -gt $((64 * 1048576)) ]; then
        echo "that call is over 64 MiB" >&2
        exit 2
    fi
}

run() {
    PY="${PYTHON:-python3}"
    if [ -f "$DIR/site.tar.xz" ]; then
        site=$(mktemp -d)
        "$PY" -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='data')" \
            "$DIR/site.tar.xz" "$site"
        export PYTHONPATH="$site:." MOCAP_MOTION_DIR="$(pwd)/$DIR/motions"
    else
        echo "SKIP packages: $DIR/site.tar.xz was not carried (sh scripts/gpu-smoke.sh prepare here, then carry it)"
        export PYTHONPATH=.
    fi
    export PYTHONUNBUFFERED=1
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
    exec "$PY" scripts/gpu_smoke.py --device "${DEVICE:-cuda}" "$@"
}

case "${1:-}" in
    prepare) prepare ;;
    *)
        if [ "${DRY_RUN:-}" = cpu ]; then
            PY="${PYTHON:-}"
            [ -n "$PY" ] || { [ -x .venv/bin/python ] && PY=.venv/bin/python; } || PY=python3
            PYTHONPATH=. PYTHONUNBUFFERED=1 exec "$PY" scripts/gpu_smoke.py --device cpu "$@"
        fi
        run "$@"
        ;;
esac
