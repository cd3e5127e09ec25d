"""The GPU check's script: it imports nothing the GPU machine lacks, refuses a missing GPU in one line, and
times a paper-size iteration's learner updates (shrunk here)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "modules",
    [
        "orchestrator.bench.device, orchestrator.bench.__main__",
        # scripts/device-warp.sh: the Warp benchmark, the simulator and its tests' imports
        "orchestrator.bench.warp_sim, workers.sim.warp_sim, workers.sim.env",
        # and its host benchmark and policy-device tests
        "orchestrator.bench.host, workers.task.policy, workers.learners.ppo",
    ],
)
def test_the_device_checks_import_only_torch_numpy_and_mujoco(modules):
    code = (
        f"import sys, {modules}\n"
        "bad = sorted({m.split('.')[0] for m in sys.modules} & {'ray', 'mlflow', 'hydra', 'omegaconf', 'scipy',"
        " 'pandas', 'matplotlib', 'yaml', 'gymnasium'})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _refused(*args: str) -> str:
    """`bench device ARGS`, which must exit 2 with no traceback: its last line on stderr."""
    out = subprocess.run(
        [sys.executable, "-m", "orchestrator.bench", "device", *args], cwd=ROOT, capture_output=True, text=True
    )
    assert out.returncode == 2 and "Traceback" not in out.stderr
    return out.stderr.strip().splitlines()[-1]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_no_gpu_is_one_line():
    assert _refused("--devices", "cuda").startswith("error: --devices=cuda: this process sees no GPU")


def test_an_unknown_compile_size_is_one_line():
    line = _refused("--compile-sizes", "huge")
    assert line.endswith("--compile-sizes: unknown size huge; expected some of paper, laptop, small")


def test_a_paper_iteration_times_eight_updates_of_each_learner(monkeypatch):
    from orchestrator.bench import device, learners

    calls = {"world_model": 0, "vae": 0}

    def small(name):
        build = learners.BUILDERS[name]

        def make(size, gen, dev):
            case = build("small", gen, dev)  # the paper's sizes take a minute here
            update = case.learner.update

            def counted(batch):
                calls[name] += 1
                return update(batch)

            case.learner.update = counted
            return case

        return make

    monkeypatch.setattr(learners, "BUILDERS", {**learners.BUILDERS, **{n: small(n) for n in calls}})
    out = device.paper_iteration(torch.device("cpu"))
    assert calls == {"world_model": 9, "vae": 9}  # one warm-up, then the iteration's eight
    assert out["iteration_s"] == pytest.approx(out["world_model_s"] + out["vae_s"]) and out["vae_s"] > 0
    text = device.format_report({"torch": "x", "threads": 1, "machine": {"cpus": 2}, "devices": {}})
    assert text.startswith("device check: torch x")


def test_a_local_pipeline_runs_without_ray_mlflow_scipy_matplotlib_or_pybullet():
    """What the GPU machine can run with a few small wheels (hydra, omegaconf, PyYAML, tqdm) and the clips
    carried in a folder (MOCAP_MOTION_DIR): the local pipeline of the tracker and AMP, with nothing tracked."""
    import pybullet_data

    motions = Path(pybullet_data.getDataPath()) / "data" / "motions"
    blocked = ("ray", "mlflow", "scipy", "pandas", "matplotlib", "gymnasium", "pybullet", "pybullet_data", "dtw")
    code = (
        f"import sys\nfor m in {blocked!r}: sys.modules[m] = None\n"
        "from orchestrator.bench.__main__ import main\n"
        "sys.exit(main(['pipeline', '--algos', 'tracker,amp', '--runtimes', 'local', '--workers', '1',"
        " '--iterations', '1', '--warmup', '0', '--envs', '2']))\n"
    )
    env = {**os.environ, "MOCAP_MOTION_DIR": str(motions)}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "tracker" in out.stdout and "amp" in out.stdout
