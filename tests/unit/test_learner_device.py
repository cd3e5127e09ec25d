"""The learners' device setting: resolution, refusal, and checkpoints that load on either device.

CI has no GPU: every learner runs here on `torch.device("cpu")` through the device path (batches moved
by `Learner.tensor`, module and optimiser placed by the base class, CPU state dicts); with CUDA (the GPU
machine) the same tests also train on it and load its checkpoint on the CPU.
"""

from __future__ import annotations

import copy
import io

import numpy as np
import pytest
import torch

from orchestrator.schema import ConfigError
from workers.learners.base import DeviceError, Schedule, resolve_device
from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorConfig, DiscriminatorLearner
from workers.learners.ppo import PPOConfig, PPOLearner, Rollout
from workers.learners.task import TaskBatch, TaskConfig, TaskLearner
from workers.learners.vae import VAEBatch, VAEConfig, VAELearner, build_controller, vae_config
from workers.learners.world_model import WorldModelBatch, WorldModelConfig, WorldModelLearner, build_world_model
from workers.models.body_state import pack

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
B, A, DT = 15, 28, 1 / 30


def test_resolution_and_refusal(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="runtime.learner_device: unknown device 'tpu'"):
        resolve_device("tpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(DeviceError, match="runtime.learner_device=cuda: this process sees no GPU"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    assert resolve_device("auto") == resolve_device("cuda") == torch.device("cuda", 0)


def test_a_ray_learner_takes_a_share_of_the_gpu_only_when_there_is_one(monkeypatch):
    from types import SimpleNamespace

    from orchestrator.runtime.base import learner_gpus

    ray = dict(_target_="orchestrator.runtime.ray.RayRuntime", learner_gpus=0.0, learner_device="auto", address=None)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    assert learner_gpus(SimpleNamespace(**ray), 2) == 0.0
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert learner_gpus(SimpleNamespace(**ray), 2) == 0.5  # both learners on the first GPU
    assert learner_gpus(SimpleNamespace(**ray), 3) == 0.3333
    assert learner_gpus(SimpleNamespace(**{**ray, "learner_device": "cpu"}), 2) == 0.0
    assert learner_gpus(SimpleNamespace(**{**ray, "learner_gpus": 1.0}), 2) == 1.0  # as set
    assert learner_gpus(SimpleNamespace(**{**ray, "address": "auto"}), 2) == 0.0  # a cluster's: set it
    local = SimpleNamespace(_target_="orchestrator.runtime.local.LocalRuntime", learner_device="auto", learner_gpus=0)
    assert learner_gpus(local, 2) == 0.0
    assert learner_gpus(SimpleNamespace(**ray), 2, gpu_workers=2) == 0.2  # with two simulating workers and the driver


def test_rollout_workers_take_a_share_of_the_gpu_only_for_a_warp_simulator_on_it(monkeypatch):
    from types import SimpleNamespace

    from orchestrator.runtime.base import worker_gpus

    ray = dict(
        _target_="orchestrator.runtime.ray.RayRuntime", worker_gpus=0.0, learner_gpus=0.0, learner_device="auto",
        address=None,
    )  # fmt: skip
    warp = SimpleNamespace(backend="warp", device="cuda")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert worker_gpus(SimpleNamespace(**ray), warp, 2, 2) == 0.2  # two workers, two learners and the driver
    assert worker_gpus(SimpleNamespace(**{**ray, "learner_device": "cpu"}), warp, 2, 2) == 0.3333
    assert worker_gpus(SimpleNamespace(**{**ray, "learner_gpus": 0.25}), warp, 2, 2) == 0.1666  # what they leave
    with pytest.raises(ConfigError, match=r"runtime.learner_gpus=1.0 for 2 learner\(s\) takes every GPU of this"):
        worker_gpus(SimpleNamespace(**{**ray, "learner_gpus": 1.0}), warp, 2, 2)  # on one GPU: none left
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 3)
    assert worker_gpus(SimpleNamespace(**{**ray, "learner_gpus": 1.0}), warp, 2, 2) == 0.3333  # learners apart
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert worker_gpus(SimpleNamespace(**{**ray, "worker_gpus": 0.1}), warp, 2, 2) == 0.1  # as set
    assert worker_gpus(SimpleNamespace(**{**ray, "address": "auto"}), warp, 2, 2) == 0.0  # a cluster's: set it
    assert worker_gpus(SimpleNamespace(**ray), SimpleNamespace(backend="warp", device="cpu"), 2, 2) == 0.0
    assert worker_gpus(SimpleNamespace(**ray), SimpleNamespace(backend="mujoco", device="cuda"), 2, 2) == 0.0
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    assert worker_gpus(SimpleNamespace(**ray), warp, 2, 2) == 0.0


def test_automatic_gpu_shares_never_add_up_to_more_than_one_gpu(monkeypatch):
    """round(1/6, 4) = 0.1667 and 6 x 0.1667 = 1.0002, which Ray refuses on a one-GPU machine; so do 7, 15 and 18
    actors. The shares are rounded down."""
    from types import SimpleNamespace

    from orchestrator.runtime.base import driver_gpus, learner_gpus, worker_gpus

    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    ray = dict(
        _target_="orchestrator.runtime.ray.RayRuntime", worker_gpus=0.0, learner_gpus=0.0, learner_device="auto",
        address=None,
    )  # fmt: skip
    warp = SimpleNamespace(backend="warp", device="cuda")
    for learners in range(1, 5):
        for workers in range(1, 20):
            # in Ray's units, 1e-4 GPU (10 x 0.1 is 1.0000000000000002 in floats)
            total = learners * round(learner_gpus(SimpleNamespace(**ray), learners, workers) * 10_000)
            total += workers * round(worker_gpus(SimpleNamespace(**ray), warp, workers, learners) * 10_000)
            total += round(driver_gpus(SimpleNamespace(**ray), warp, workers, learners) * 10_000)
            assert 9_900 < total <= 10_000, (learners, workers, total)
    assert learner_gpus(SimpleNamespace(**ray), 1, gpu_workers=4) == 0.1666  # with four workers and the driver


class _Reserved(Exception):
    """Raised by `_ReserveOnly.reserve` to stop the trainer before it spawns anything."""


class _ReserveOnly:
    def reserve(self, bundles):
        raise _Reserved(bundles)


def test_the_trainer_reserves_the_rollout_workers_gpu_shares(monkeypatch, tmp_path, character):
    pytest.importorskip("mujoco_warp")
    from orchestrator.compose import compose, validate
    from orchestrator.tracking.base import NoOpLogger
    from orchestrator.trainer import Trainer

    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    common = [f"run_dir={tmp_path}", "scale=smoke", "runtime=ray", "runtime.pin_cores=shared", "sim.backend=warp"]
    shares = {}
    for name, extra in (("auto", ["sim.device=cuda"]), ("set", ["sim.device=cuda", "runtime.worker_gpus=0.1"])):
        cfg = validate(compose([*common, *extra]))
        with pytest.raises(_Reserved) as e:
            Trainer(cfg, _ReserveOnly(), NoOpLogger(), character)
        bundles = e.value.args[0]
        shares[name] = [b.gpus for b in bundles]
    # controlvae: replay, world model, VAE, two rollout workers, then the driver's own bundle (it evaluates on the
    # workers' GPU simulator): the two learners, two workers and the driver share a GPU
    assert shares["auto"] == [0.0, 0.2, 0.2, 0.2, 0.2, 0.2]
    assert shares["set"] == [0.0, 0.5, 0.5, 0.1, 0.1]  # the workers' as set, the learners share theirs, no driver's
    cfg = validate(compose([*common, "sim.device=cpu"]))
    with pytest.raises(_Reserved) as e:
        Trainer(cfg, _ReserveOnly(), NoOpLogger(), character)
    assert [b.gpus for b in e.value.args[0]] == [0.0, 0.5, 0.5, 0.0, 0.0]  # Warp on the CPU: no GPU for workers


def walk_windows(walk_run, n: int = 6, steps: int = 3) -> np.ndarray:
    frames = np.arange(n)[:, None] + np.arange(steps + 1)
    kin = walk_run.state(np.zeros(frames.size, int), frames.ravel())
    return pack(kin).reshape(n, steps + 1, B, 13)


def learners(walk_run, device):
    """(name, build(device) -> learner, the batch one update takes) for every learner kind."""
    states = walk_windows(walk_run)
    actions = np.random.default_rng(0).normal(0, 0.1, (6, 3, A)).astype(np.float32)
    wm_cfg = WorldModelConfig(hidden=(16,))
    small = dict(latent_dim=4, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,), lr=1e-3, beta=Schedule(0.1))

    def vae(objective, prior, **kw):
        def build(dev):
            wm = build_world_model(B, A, wm_cfg, DT) if objective != "pulse" else None
            cfg = vae_config(objective=objective, prior=prior, **small, **kw)
            return VAELearner(B, A, cfg, wm, seed=0, device=dev)

        return build

    def task(dev):
        controller = build_controller(B, A, VAEConfig(**small))
        config = TaskConfig(task="heading", hidden=(16,), helper_hidden=(16,), sigma=0.1, rollout_steps=3)
        return TaskLearner(controller, build_world_model(B, A, wm_cfg, DT), A, config, device=dev)

    goals = np.tile(np.array([0.5, 1.0], np.float32), (6, 3, 1))
    obs = np.random.default_rng(1).normal(size=(16, 4, 12)).astype(np.float32)
    rollout = Rollout(
        obs=obs, actions=np.zeros((16, 4, 2), np.float32), log_probs=np.zeros((16, 4), np.float32),
        rewards=np.ones((16, 4), np.float32), dones=np.zeros((16, 4), np.float32), last_obs=obs[-1],
    )  # fmt: skip
    ppo_cfg = PPOConfig(policy_hidden=(16,), value_hidden=(16,), optimizer="adam", minibatch_size=32)
    disc_obs = np.random.default_rng(2).normal(size=(32, 20))  # transitions (Φ(s), Φ(s′)).astype(np.float32)
    disc = DiscriminatorBatch(disc_obs, disc_obs + 1.0)
    return [
        ("world_model", lambda d: WorldModelLearner(B, A, DT, wm_cfg, d), WorldModelBatch(states, actions)),
        ("vae-controlvae", vae("controlvae", "conditional"), VAEBatch(states, states.copy())),
        ("vae-physicsvae", vae("physicsvae", "standard_normal"), VAEBatch(states, actions=actions)),
        ("vae-pulse", vae("pulse", "learned", goal="mimic"), VAEBatch(states, states.copy(), actions)),
        ("task", task, TaskBatch(states[:, 0], goals)),
        ("ppo", lambda d: PPOLearner(12, 2, ppo_cfg, d), rollout),
        ("discriminator", lambda d: DiscriminatorLearner(10, DiscriminatorConfig(hidden=(16,)), 0, d), disc),
    ]


def step(learner, batch) -> dict[str, float]:
    return learner.train_on_rollout(batch) if isinstance(learner, PPOLearner) else learner.update(batch)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("index", range(7))
def test_every_learner_trains_on_its_device_and_its_checkpoint_loads_on_the_cpu(walk_run, device, index):
    """Update on `device`: weights published as CPU tensors, a CPU state dict; the checkpoint (saved and
    loaded through bytes, as the trainer does, map_location cpu) into a CPU learner holds the same weights,
    and on the CPU gives exactly the same next update (across devices the noise streams differ: the twin's
    update is only checked to be finite)."""
    name, build, batch = learners(walk_run, device)[index]
    torch.manual_seed(0)
    learner = build(torch.device(device))
    assert next(learner.module.parameters()).device.type == device
    step(learner, batch)
    weights = learner.get_weights()
    assert all(t.device.type == "cpu" for t in weights.state.values()), name
    buffer = io.BytesIO()
    torch.save(learner.state_dict(), buffer)
    state = torch.load(io.BytesIO(buffer.getvalue()), map_location="cpu", weights_only=False)
    torch.manual_seed(0)
    twin = build(torch.device("cpu"))
    twin.load_state_dict(state)
    for k, v in twin.get_weights().state.items():
        torch.testing.assert_close(v, weights.state[k], rtol=0, atol=0, msg=f"{name}: {k}")
    if device != "cpu":
        assert np.isfinite(step(twin, batch)["loss"]), name
        return
    if name == "discriminator":  # its replay of policy samples and its draws from it are not in the state
        twin.replay, twin.rng = copy.deepcopy(learner.replay), copy.deepcopy(learner.rng)
    if hasattr(learner, "generator"):  # the VAE's sampling stream is the actor's, not the checkpoint's
        twin.generator.set_state(learner.generator.get_state())
    torch.manual_seed(1)
    want = step(learner, batch)
    torch.manual_seed(1)
    got = step(twin, batch)
    assert got["loss"] == want["loss"], name


def test_building_a_learner_or_a_policy_reseeds_no_gpu_and_restores_the_cpu_generator(monkeypatch):
    """`torch.manual_seed` reseeds every CUDA generator too (lazily, on a machine without one), and
    `fork_rng(devices=[])` restores only the CPU's: a GPU run's noise would depend on construction order."""
    from workers.policies import VAEPolicy

    reseeded: list[int] = []
    monkeypatch.setattr(torch.cuda, "manual_seed_all", reseeded.append)
    torch.random.default_generator.manual_seed(1234)
    before = torch.random.get_rng_state()
    PPOLearner(12, 2, PPOConfig(policy_hidden=(8,), value_hidden=(8,)))
    DiscriminatorLearner(10, DiscriminatorConfig(hidden=(16,)), 3)
    VAEPolicy(B, A, VAEConfig(latent_dim=4, encoder_hidden=(16,), policy_hidden=(16,)))
    assert reseeded == []
    assert torch.equal(torch.random.get_rng_state(), before)
    first = PPOLearner(12, 2, PPOConfig(policy_hidden=(8,), value_hidden=(8,), seed=5)).module.state_dict()
    again = PPOLearner(12, 2, PPOConfig(policy_hidden=(8,), value_hidden=(8,), seed=5)).module.state_dict()
    assert all(torch.equal(first[k], again[k]) for k in first)  # still seeded
