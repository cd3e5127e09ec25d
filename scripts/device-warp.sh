#!/bin/sh
# The MuJoCo Warp checks and benchmarks on the GPU machine (issue 25; docs/warp.md, "On a GPU"). That machine has
# PyTorch (CUDA), NumPy, pytest, absl-py and etils but no network, takes other packages only as files carried with
# the working tree (64 MiB a call), and keeps nothing between calls. Each call carries the GPU smoke's packages
# (`.device/smoke`: warp-lang, MuJoCo and MuJoCo Warp, Hydra, xz-packed under 64 MiB with the tree; see
# scripts/gpu-smoke.sh) and stands alone.
#
# Here (network), once:  sh scripts/device-warp.sh prepare      (the same as sh scripts/gpu-smoke.sh prepare)
# There:  STEPS=... sh scripts/device-warp.sh run               with carry [".device/smoke"]
# STEPS (default "tests equivalence sim host pipeline") runs some of the checks, so that each call stays under 8
# minutes (all of them, with a cold Warp cache, are likely over 10: one call per step or two); QUICK=1 (or
# WORLDS=a,b,...) benchmarks fewer world counts. The checks write their output under $OUT when it is set: the Warp
# tests on cuda (and the policies' on cuda against the CPU), the equivalence run, `bench sim --backend warp --device
# cuda` against MuJoCo C on all the machine's cores, `bench host --device cuda --sim mujoco,warp` (a worker's host
# work per control step beside its policy on the GPU, its state's features and rewards computed on the host from
# MuJoCo C's arrays or on the GPU from MuJoCo Warp's), and `bench pipeline --runtimes local --sim mujoco,warp` for the
# tracker and AMP (MuJoCo C on one thread there: the local runtime steps one worker in the benchmark's process).
set -e
cd "$(dirname "$0")/.."
DIR=.device/smoke
DEVICE="${WARP_DEVICE:-cuda}"
PY="${PYTHON:-python3}"

run_checks() {
    [ -f "$DIR/site.tar.xz" ] || { echo "$DIR/site.tar.xz was not carried: sh $0 prepare here, then carry it" >&2; exit 2; }
    site=$(PYTHON="$PY" sh scripts/gpu-smoke.sh unpack)
    out="${OUT:-$site/out}"
    mkdir -p "$out"
    export PYTHONPATH="$site:." PYTHONUNBUFFERED=1 MOCAP_WARP_DEVICE="$DEVICE" MOCAP_MOTION_DIR="$site/motions"
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
    prepare) exec sh scripts/gpu-smoke.sh prepare ;;
    run) run_checks ;;
    *) echo "usage: sh scripts/device-warp.sh prepare | run" >&2; exit 2 ;;
esac
