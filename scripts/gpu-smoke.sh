#!/bin/sh
# The GPU smoke in one call (issue 45): on a GPU machine with PyTorch (CUDA), NumPy and Python 3.12 but no network,
# which takes other packages only as files carried with the working tree (64 MiB a call) and keeps nothing between
# calls. Prints one line per check (PASS, FAIL or SKIP, its seconds, what it saw: scripts/gpu_smoke.py) and exits 1
# when one fails.
#
# Here (network), once:  sh scripts/gpu-smoke.sh prepare      (make gpu-smoke)
#   installs the packages the checks need that the GPU machine does not have (MuJoCo, MuJoCo Warp and warp-lang,
#   Hydra, dtw-python: constraints.txt's pins; its image has torch, NumPy, SciPy, matplotlib, PyYAML, tqdm, psutil,
#   absl-py and etils) for Python 3.12 into a folder, drops what no check uses (tests, examples, MuJoCo's studio and
#   docs, Warp's CPU compiler warp-clang.so: the device's Warp runs on CUDA), zeroes warp.so's GPU code for
#   architectures other than the machine's (scripts/keep_cubins.py; KEEP_SM=90, the H100's and H200's), adds the
#   bundled clips, packs it with xz's x86 filter as .device/smoke/site.tar.xz (warp.so is 299 MB: 78 MB with plain
#   xz -9e, 58 MiB with the filter; the whole bundle, the other GPUs' code zeroed, 61 MiB: with the tree, 63.5 of
#   the call's 64 MiB on 2026-12-07), and prints what the call carries. About 5 minutes (xz on one core).
# There:  sh scripts/gpu-smoke.sh        with carry [".device/smoke"]
#   unpacks it (Python's tarfile, a few seconds) and runs the checks on cuda.
# Here, the dry run:  DRY_RUN=cpu sh scripts/gpu-smoke.sh     the same checks on the CPU and Warp's CPU device,
#   with this checkout's environment (PYTHON, else .venv/bin/python, else python3).
set -e
cd "$(dirname "$0")/.."
DIR=.device/smoke
DEVICE_PY="${DEVICE_PY:-3.12}"
# Not glfw or PyOpenGL (17 MB): nothing the checks run renders (eval.video=false).
PACKAGES="mujoco==4.0.0 mujoco-core==4.0.0 hydra-core==1.3.8 omegaconf==2.3.1 dtw-python==1.9.0 warp-lang==1.19.0
mujoco-warp==4.0.0"
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
site = work / "site"
for tests in [p for p in site.rglob("*") if p.is_dir() and p.name in ("tests", "test_data", "testdata")]:
    shutil.rmtree(tests, ignore_errors=True)
for test in [*site.glob("mujoco/*_test.py"), *site.glob("mujoco_warp/_src/*_test.py")]:
    test.unlink()
# MuJoCo's studio, viewer, docs, C headers, plugins (our character uses none), USD and system-identification tools;
# Warp's examples, type stubs and CPU compiler (warp-clang.so: the device's Warp runs on CUDA).
for unused in ("mujoco/studio", "mujoco/doc", "mujoco/include", "mujoco/plugin", "mujoco/usd", "mujoco/sysid",
               "mujoco/introspect", "warp/examples"):
    shutil.rmtree(site / unused, ignore_errors=True)
for unused in [*site.glob("mujoco/_simulate*.so"), site / "warp/__init__.pyi", site / "warp/bin/warp-clang.so"]:
    unused.unlink()
EOF
    # warp.so's SASS for GPUs other than the machine's (sm_90: H100, H200) zeroed in place (scripts/keep_cubins.py).
    "$PY" scripts/keep_cubins.py "$work/site/warp/bin/warp.so" --keep "${KEEP_SM:-90}"
    # The clips the checks and the Warp tests load (pybullet's wheel, which has them, is too large to carry).
    cp -r "$("$PY" -c 'import pybullet_data; print(pybullet_data.getDataPath())')/data/motions" "$work/site/motions"
    rm -rf "$DIR" && mkdir -p "$DIR"
    tar -C "$work/site" -cf - . | xz -T1 --x86 --lzma2=preset=9e,dict=192MiB >"$DIR/site.tar.xz"
    rm -rf "$work"
    # What travels with it: tracked files and untracked ones git does not ignore.
    tree=$(git ls-files -z -c -o --exclude-standard | xargs -0 du -cb | tail -1 | cut -f1)
    carried=$(du -cb "$DIR" | tail -1 | cut -f1)
    echo "$DIR: $((carried / 1048576)) MiB, the tree $((tree / 1048576)) MiB; carry [\"$DIR\"]: sh scripts/gpu-smoke.sh"
    if [ $((carried + tree)) -gt $((64 * 1048576)) ]; then
        echo "that call is over 64 MiB" >&2
        exit 2
    fi
}

# The carried packages unpacked into a new folder (Python's tarfile, a few seconds), whose path it prints; the
# clips are its motions/. scripts/device-warp.sh unpacks them so too.
unpack() {
    site=$(mktemp -d)
    "${PYTHON:-python3}" -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='data')" \
        "$DIR/site.tar.xz" "$site"
    echo "$site"
}

run() {
    PY="${PYTHON:-python3}"
    if [ -f "$DIR/site.tar.xz" ]; then
        site=$(unpack)
        export PYTHONPATH="$site:." MOCAP_MOTION_DIR="$site/motions"
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
    unpack) unpack ;;
    *)
        if [ "${DRY_RUN:-}" = cpu ]; then
            PY="${PYTHON:-}"
            [ -n "$PY" ] || { [ -x .venv/bin/python ] && PY=.venv/bin/python; } || PY=python3
            PYTHONPATH=. PYTHONUNBUFFERED=1 exec "$PY" scripts/gpu_smoke.py --device cpu "$@"
        fi
        run "$@"
        ;;
esac
