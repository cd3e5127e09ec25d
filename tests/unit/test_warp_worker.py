"""The rollout worker on MuJoCo Warp (Warp's CPU device; `MOCAP_WARP_DEVICE=cuda` on the GPU machine): it resumes
exactly from a checkpoint, and beside the device's state every kind of policy reads the body states, acts and records
there, the simulator takes the actions as they are, and the trajectory is copied to the host once per collect.
The simulator itself against MuJoCo C: test_warp_sim.py. Stepping compiles MuJoCo Warp's kernels the first time on a
machine, hence `slow`.
"""

from __future__ import annotations

import copy
import os

import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp")

from workers.body.features import amp_features  # noqa: E402
from workers.learners.base import Weights  # noqa: E402
from workers.learners.vae import VAEConfig, build_controller  # noqa: E402
from workers.motion.library import MotionLibrary  # noqa: E402
from workers.sim.env import SimConfig  # noqa: E402
from workers.sim.warp_sim import WarpSim  # noqa: E402

DEVICE = os.environ.get("MOCAP_WARP_DEVICE", "cpu")  # scripts/device-warp.sh runs these on cuda


@pytest.fixture(scope="module")
def library(character, clip_cache):
    """A looping clip (walk) and a one-shot one (kick)."""
    return MotionLibrary.load(character, ["humanoid3d_walk", "humanoid3d_kick"], fps=30, cache_dir=clip_cache)


@pytest.mark.slow
def test_a_rollout_worker_on_warp_resumes_exactly(character, library):
    """The rollout worker builds its simulator with make_sim and checkpoints it through save_state/restore_state.
    Its policy runs on the simulator's device (on a GPU, the GPU: float rounding then differs between runs)."""
    from workers.learners.base import Weights
    from workers.learners.vae import VAEConfig, build_controller
    from workers.policies import VAEPolicy
    from workers.rollout import RolloutWorker

    vae = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(64,))
    torch.manual_seed(0)
    controller = build_controller(character.num_bodies, character.num_actions, vae)
    weights = Weights(1, {k: v.clone() for k, v in controller.state_dict().items()})
    config = SimConfig(backend="warp", device=DEVICE, max_episode_steps=4)  # episodes end (and reset) every four steps

    def worker(seed):
        policy = VAEPolicy(character.num_bodies, character.num_actions, vae, 0.5)
        w = RolloutWorker(character, library, 2, policy, sim_config=config, seed=seed)
        w.set_weights(weights)
        return w

    first = worker(seed=4)
    assert type(first.sim) is WarpSim and first.policy.device.type == torch.device(DEVICE).type
    first.collect(3)
    state = copy.deepcopy(first.state_dict())
    expected = first.collect(6)
    assert expected.done.any()  # the comparison covers resets
    resumed = worker(seed=99)
    resumed.load_state_dict(state)
    got = resumed.collect(6)
    for name in ("done", "clip_id", "frame"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)
    for name in ("states", "next_states", "actions"):  # bit for bit on the CPU
        tol = 0.0 if DEVICE == "cpu" else 1e-3
        np.testing.assert_allclose(getattr(got, name), getattr(expected, name), atol=tol, rtol=0, err_msg=name)


@pytest.mark.slow
def test_an_amp_worker_on_warp_observes_and_records_on_the_device(character, library):
    """AMP's worker on MuJoCo Warp: the policy's observation s and the recorder's Φ(s) are made on the device
    (float32 torch); they are NumPy's of the same states to float rounding, and a reset environment's next
    Φ(s_t) is its reference start's."""
    from workers.body.features import StateLayout
    from workers.learners.ppo import PPOConfig, build_actor_critic
    from workers.models.body_state import features_np
    from workers.policies import GaussianPolicy
    from workers.recorders import AMPFeatures
    from workers.rollout import RolloutWorker

    torch.manual_seed(0)
    module = build_actor_critic(StateLayout(character.num_bodies).dim, character.num_actions, PPOConfig())
    config = SimConfig(backend="warp", device=DEVICE, max_episode_steps=3)
    policy = GaussianPolicy(module, "state")
    worker = RolloutWorker(character, library, 3, policy, config, seed=1, recorders=[AMPFeatures(character)])
    traj = worker.collect(5)
    for t in range(5):
        np.testing.assert_allclose(traj.extras["obs"][t], features_np(traj.states[t]), rtol=0, atol=1e-5)
    before, after = traj.extras["amp_obs"], traj.extras["amp_next_obs"]
    assert traj.done[2].all() and not traj.done[:2].any()  # every episode ends after three steps
    np.testing.assert_array_equal(before[1:3], after[0:2])
    start = library.state(traj.clip_id[3], traj.frame[3])
    np.testing.assert_allclose(before[3], amp_features(character, start), rtol=0, atol=1e-4)
    assert np.abs(before[3] - after[2]).max() > 1e-2  # the reset's Φ, not the fall's


@pytest.mark.slow
def test_every_kind_of_policy_collects_with_the_body_states_on_the_device(character, library):
    """Beside MuJoCo Warp the worker keeps the body states on the device (every policy here reads them there)
    and copies the trajectory's once: its arrays are NumPy, each step's
    next states are the following step's states but where an episode ended, and a mimic observation made
    from the device's states is NumPy's of the stored ones."""
    from workers.learners.ppo import PPOConfig, build_actor_critic
    from workers.learners.task import TaskConfig
    from workers.learners.vae import VAEConfig
    from workers.models.body_state import features_np
    from workers.models.tracking_goal import mimic_goal
    from workers.policies import GaussianPolicy, VAEPolicy, observation_dim
    from workers.rollout import RolloutWorker
    from workers.task.policy import TaskRolloutPolicy

    b, a = character.num_bodies, character.num_actions
    skill = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(32,))
    torch.manual_seed(0)
    task = TaskRolloutPolicy(b, a, TaskConfig(task="point_goal", sigma=0.5, hidden=(16,), helper_hidden=(16,)), 30.0)
    task.configure(
        {"skill": {"config": skill, "module": build_controller(b, a, skill).state_dict(), "prior_action": True}}
    )
    mimic = GaussianPolicy(build_actor_critic(observation_dim("mimic", 16 * b + 3), a, PPOConfig()), "mimic")
    config = SimConfig(backend="warp", device=DEVICE, max_episode_steps=3)
    for name, policy in (("vae", VAEPolicy(b, a, skill)), ("mimic", mimic), ("task", task)):
        worker = RolloutWorker(character, library, 3, policy, config, seed=5)
        if name == "vae":
            worker.set_weights(Weights(1, build_controller(b, a, skill).state_dict()))
        traj = worker.collect(5)
        assert isinstance(traj.states, np.ndarray) and traj.states.dtype == np.float32, name
        assert traj.done[2].all() and not traj.done[[0, 1, 3]].any(), name
        np.testing.assert_array_equal(traj.next_states[[0, 1, 3]], traj.states[[1, 2, 4]], err_msg=name)
        assert np.abs(traj.next_states[2] - traj.states[3]).max() > 1e-3, name  # reset: a new start
        if name == "mimic":
            obs = traj.extras["last_obs"]  # of the states after the last step, made on the device
            s = features_np(traj.next_states[-1])
            ref = torch.from_numpy(worker.sim.reference_next_body_states())  # on the host, from the library
            goal = mimic_goal(torch.from_numpy(traj.next_states[-1]), ref).numpy()
            on_device = worker.sim.tracking_goal("mimic", traj.next_states[-1]).cpu()
            np.testing.assert_allclose(on_device, goal, rtol=0, atol=1e-4)
            ref_s = worker.sim.reference_next_features()
            np.testing.assert_array_equal(worker.sim.tracking_goal("reference", traj.next_states[-1]).cpu(), ref_s)
            np.testing.assert_allclose(obs, np.concatenate((s, goal), axis=-1), rtol=0, atol=1e-4)


@pytest.mark.slow
def test_the_actions_stay_on_the_device_and_are_the_ones_applied(character, library, monkeypatch):
    """Beside MuJoCo Warp a policy's actions stay tensors on the device: the simulator takes them there and
    the trajectory stores what it applied. A residual policy's offset is the reference's next PD targets,
    looked up on the device; an expert acting on the device adds its noise there."""
    from workers.learners.ppo import PPOConfig, build_actor_critic
    from workers.policies import ExpertPolicy, GaussianPolicy, observation_dim
    from workers.rollout import RolloutWorker

    b, a = character.num_bodies, character.num_actions
    torch.manual_seed(0)
    module = build_actor_critic(observation_dim("imitation", 16 * b + 3), a, PPOConfig())
    expert = {"kind": "ppo", "config": PPOConfig(), "module": module.state_dict(), "observation": "imitation"}
    config = SimConfig(backend="warp", device=DEVICE, max_episode_steps=3)
    applied: list[torch.Tensor] = []
    advance = WarpSim._advance
    monkeypatch.setattr(WarpSim, "_advance", lambda self, x: applied.append(x.clone()) or advance(self, x))
    for name, policy in (("ppo", GaussianPolicy(module, "imitation", residual=True)), ("expert", ExpertPolicy(b, a))):
        applied.clear()
        worker = RolloutWorker(character, library, 3, policy, config, seed=5)
        if name == "expert":
            worker.set_weights(Weights(1, {**expert, "residual": True}))
        traj = worker.collect(5)
        assert all(isinstance(x, torch.Tensor) and x.device == worker.sim.torch_device for x in applied), name
        assert isinstance(traj.actions, np.ndarray) and traj.actions.dtype == np.float32, name
        np.testing.assert_array_equal(traj.actions, torch.stack(applied).cpu().numpy(), err_msg=name)
        if name == "ppo":  # the applied PD targets are the sample plus the reference's next pose's
            base = library.pd_targets(traj.clip_id, traj.frame + 1)
            np.testing.assert_allclose(traj.actions - traj.extras["action"], base, rtol=0, atol=1e-5)


@pytest.mark.slow
def test_a_task_policy_acts_and_records_on_the_device(character, library, monkeypatch):
    """The task policies read the body states on the device, act there (the simulator gets tensors) and compute
    their rewards there: e^(-L_g) and the point goal's progress d_{t-1} - d_t equal NumPy's of the stored
    states and goals; the goals are drawn around the roots, and a reset's goal around its new root."""
    from workers.learners.ppo import PPOConfig
    from workers.learners.task import TaskConfig
    from workers.losses.task import task_terms
    from workers.rollout import RolloutWorker
    from workers.task.goals import DEFAULT_RANGES
    from workers.task.policy import TaskPPOPolicy, TaskRolloutPolicy

    b, a = character.num_bodies, character.num_actions
    skill = VAEConfig(latent_dim=8, encoder_hidden=(32,), policy="mlp", policy_hidden=(32,))
    torch.manual_seed(0)
    payload = {"config": skill, "module": build_controller(b, a, skill).state_dict(), "prior_action": True}
    exp = TaskConfig(task="point_goal", sigma=0.5, hidden=(16,), helper_hidden=(16,), change_rate=3.0)
    progress = TaskConfig(task="point_goal", hidden=(16,), reward="progress", trainer="ppo", change_rate=3.0)
    applied: list[object] = []
    advance = WarpSim._advance
    monkeypatch.setattr(WarpSim, "_advance", lambda self, x: applied.append(type(x)) or advance(self, x))
    config = SimConfig(backend="warp", device=DEVICE, max_episode_steps=3)
    monkeypatch.setitem(DEFAULT_RANGES, "distance", (1.0, 1.0))  # every point goal 1 m from its root when drawn
    for policy in (TaskRolloutPolicy(b, a, exp, 30.0), TaskPPOPolicy(b, a, progress, 30.0, PPOConfig())):
        applied.clear()
        worker = RolloutWorker(character, library, 3, policy, config, seed=6)
        policy.configure({"skill": payload})
        traj = worker.collect(5)
        assert applied == [torch.Tensor] * 5
        goal = traj.extras["goal"]
        distance = np.linalg.norm(goal - traj.states[:, :, 0, :2], axis=-1)
        np.testing.assert_allclose(distance[[0, 3]], 1.0, rtol=0, atol=1e-5)  # at the start and the resets
        assert np.abs(goal[3] - goal[2]).min() > 1e-2  # new goals around the new roots
        terms = {
            k: v.numpy()
            for k, v in task_terms("point_goal", torch.from_numpy(traj.next_states), torch.from_numpy(goal)).items()
        }
        if policy.config.reward == "progress":
            want = distance - terms["distance"]
        else:
            want = np.exp(-sum(policy.config.weights[k] * v for k, v in terms.items()))
            assert traj.extras["helper_deviation"].dtype == np.float32 and traj.extras["helper_deviation"].min() > 0
        assert np.abs(want).max() > 1e-3
        np.testing.assert_allclose(traj.extras["reward"], want, rtol=0, atol=1e-5)
        np.testing.assert_allclose(traj.extras["reward/distance"], terms["distance"], rtol=0, atol=1e-5)
