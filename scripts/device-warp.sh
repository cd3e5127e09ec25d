#!/bin/sh
# The MuJoCo Warp checks on the GPU machine (issue 25; docs/warp.md, "On a GPU"). That machine has PyTorch (CUDA),
# NumPy, pytest, absl-py and etils but no network, and takes other packages only as files carried with the working
# tree, 64 MiB a call. warp-lang's wheel is about 142 MiB, so it travels in parts over consecutive calls, each
# stashed aside on the machine (it keeps its files while it stays warm between calls), and the last call joins them,
# checks the join against the wheel's SHA-256, installs and runs the checks.
#
# Here (network):  sh scripts/device-warp.sh prepare
#   downloads the wheels for the machine's Python (DEVICE_PY, 3.12), splits warp-lang into .device/warp/part-*
#   and prints the calls to make, one per part, each with what it carries.
# There, in order, while the machine stays warm (the device tool's `run`, carry as printed):
#   sh scripts/device-warp.sh stash          (once per part but the last)
#   sh scripts/device-warp.sh run            (the last part and .device/warp/wheels: join, install, check)
# STEPS (default "tests equivalence sim host pipeline") runs some of the checks, so that a call stays under 8
# minutes on a warm machine (all of them, with a cold Warp cache, are likely over 10); QUICK=1 (or WORLDS=a,b,...)
# benchmarks fewer world counts. The checks write their output under $OUT when it is
# set: the Warp tests on cuda (and the policies' on cuda against the CPU), the equivalence run, `bench sim --backend
# warp --device cuda` against MuJoCo C on all the machine's cores, and `bench host --device cuda --sim mujoco,warp` (a
# worker's host work per control step beside its policy on the GPU, its state's features and rewards computed on
# the host from MuJoCo C's arrays or on the GPU from MuJoCo Warp's), and `bench pipeline --runtimes local --sim
# mujoco,warp` for the tracker and AMP (MuJoCo C on one thread there: the local runtime steps one worker in the
# benchmark's process).
set -e
cd "$(dirname "$0")/.."
DIR=.device/warp
STASH="${DEVICE_WARP_STASH:-$HOME/.cache/mocap-device-warp}"
DEVICE_PY="${DEVICE_PY:-3.12}"
DEVICE="${WARP_DEVICE:-cuda}"  # a dry run of the whole path here: WARP_DEVICE=cpu DEVICE_PY=3.11 PYTHON=.venv/bin/python
PY="${PYTHON:-python3}"
PART_MIB="${PART_MIB:-58}"
WARP=warp-lang==1.19.0
SMALL="mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw==2.11.0 pyopengl==3.1.10 mujoco-warp==4.0.0"
# What `bench pipeline --runtimes local` needs beside those (no ray, mlflow or scipy on its path; constraints.txt's pins).
PIPELINE="hydra-core==1.3.8 omegaconf==2.3.1 PyYAML==6.0.3 tqdm==4.70.1"
ANTLR=antlr4-python3-runtime==4.9.3  # hydra's parser runtime: an sdist only, built into a wheel here

download() {
    dest=$1
    shift
    "$PY" -m pip download --quiet --no-deps --only-binary=:all: --implementation cp --python-version "$DEVICE_PY" \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux2014_x86_64 \
        -d "$dest" "$@"
}

prepare() {
    rm -rf "$DIR" && mkdir -p "$DIR/wheels" "$DIR/big"
    # shellcheck disable=SC2086
    download "$DIR/wheels" $SMALL $PIPELINE
    "$PY" -m pip wheel --quiet --no-deps -w "$DIR/wheels" "$ANTLR"
    download "$DIR/big" "$WARP"
    # The bundled clips come with pybullet (a large wheel), which the GPU machine lacks: carry a copy of them
    # (1.4 MiB), read through MOCAP_MOTION_DIR.
    cp -r "$("$PY" -c 'import pybullet_data; print(pybullet_data.getDataPath())')/data/motions" "$DIR/wheels/motions"
    wheel=$(ls "$DIR"/big/warp_lang-*.whl)
    name=$(basename "$wheel")
    (cd "$DIR/big" && sha256sum "$name") >"$DIR/wheels/warp.sha256"
    split -b "${PART_MIB}M" -d -a 1 "$wheel" "$DIR/part-"
    rm -rf "$DIR/big"
    tree=$(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)
    parts=$(ls "$DIR"/part-*)
    last=$(echo "$parts" | tail -1)
    echo "$name: $(echo "$parts" | wc -l) parts of at most $PART_MIB MiB; the tree is $((tree / 1048576)) MiB"
    for p in $parts; do
        if [ "$p" = "$last" ]; then
            size=$(du -cb "$p" "$DIR/wheels" | tail -1 | cut -f1)
            echo "  carry [\"$p\", \"$DIR/wheels\"]: sh scripts/device-warp.sh run    ($(((size + tree) / 1048576)) MiB)"
        else
            size=$(du -b "$p" | cut -f1)
            echo "  carry [\"$p\"]: sh scripts/device-warp.sh stash    ($(((size + tree) / 1048576)) MiB)"
        fi
        if [ $((size + tree)) -gt $((64 * 1048576)) ]; then
            echo "that call is over 64 MiB: set PART_MIB lower" >&2
            exit 2
        fi
    done
}

stash() {
    mkdir -p "$STASH"
    found=0
    for p in "$DIR"/part-*; do
        [ -f "$p" ] || continue
        cp "$p" "$STASH/" && found=1 && echo "stashed $(basename "$p") in $STASH"
    done
    [ "$found" = 1 ] || { echo "no part of the wheel was carried ($DIR/part-*): carry one" >&2; exit 2; }
    ls -l "$STASH"
}

install() {
    stash
    [ -f "$DIR/wheels/warp.sha256" ] || { echo "$DIR/wheels was not carried with the last part" >&2; exit 2; }
    name=$(cut -d' ' -f3 "$DIR/wheels/warp.sha256")
    cat "$STASH"/part-* >"$STASH/$name"
    if ! (cd "$STASH" && sha256sum --check --quiet "$DIR_ABS/wheels/warp.sha256"); then
        echo "the joined $name does not match its SHA-256: a part is missing or stale in $STASH" >&2
        ls -l "$STASH" >&2
        exit 2
    fi
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$STASH/site" \
        "$STASH/$name" "$DIR"/wheels/*.whl
}

run_checks() {
    DIR_ABS=$(pwd)/$DIR
    install
    out="${OUT:-$STASH/out}"
    mkdir -p "$out"
    export PYTHONPATH="$STASH/site:." PYTHONUNBUFFERED=1 MOCAP_WARP_DEVICE="$DEVICE" MOCAP_MOTION_DIR="$DIR_ABS/wheels/motions"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
    "$PY" -c "import warp, mujoco_warp, torch; warp.init(); print('warp', warp.__version__, 'torch', torch.__version__)"
    status=0
    steps="${STEPS:-tests equivalence sim host pipeline}"
    case " $steps " in *" tests "*)
    "$PY" -m pytest -q -m "" -p no:cacheprovider tests/unit/test_warp_physics.py tests/unit/test_warp_sim.py \
        tests/unit/test_warp_worker.py tests/unit/test_warp_tracking.py tests/unit/test_policy_device.py \
        >"$out/tests.txt" 2>&1 || status=1
    tail -n 15 "$out/tests.txt" ;; esac
    case " $steps " in *" equivalence "*)
    "$PY" scripts/warp_equivalence.py --device "$DEVICE" --control-steps 300 >"$out/equivalence.txt" 2>&1 || status=1
    tail -n 20 "$out/equivalence.txt" ;; esac
    if [ -n "$QUICK" ]; then worlds=1024,8192; else worlds=1024,4096,16384,65536; fi
    case " $steps " in *" sim "*)
    "$PY" -m orchestrator.bench sim --backend warp --device "$DEVICE" --worlds "${WORLDS:-$worlds}" \
        --out "$out/bench-sim.json" >"$out/bench-sim.txt" 2>&1 || status=1
    tail -n 12 "$out/bench-sim.txt" ;; esac
    case " $steps " in *" host "*)
    "$PY" -m orchestrator.bench host --device "$DEVICE" --policies vae,vae-paper,tracker,actor-critic,task \
        --envs "${HOST_ENVS:-1024,4096,16384}" --sim mujoco,warp \
        --out "$out/bench-host.json" >"$out/bench-host.txt" 2>&1 || status=1
    tail -n 26 "$out/bench-host.txt" ;; esac
    # End to end, local runtime (no Ray there), nothing tracked: the tracker and AMP on each engine.
    case " $steps " in *" pipeline "*)
    "$PY" -m orchestrator.bench pipeline --algos tracker,amp --runtimes local --workers 1 \
        --envs "${PIPELINE_ENVS:-1024}" --iterations 2 --warmup 1 --sim mujoco,warp --sim-device "$DEVICE" \
        --out "$out/bench-pipeline.json" >"$out/bench-pipeline.txt" 2>&1 || status=1
    tail -n 8 "$out/bench-pipeline.txt" ;; esac
    exit $status
}

case "$1" in
    prepare) prepare ;;
    stash) stash ;;
    run) run_checks ;;
    *) echo "usage: sh scripts/device-warp.sh prepare | stash | run" >&2; exit 2 ;;
esac
