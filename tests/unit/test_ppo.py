"""PPO: GAE against a plain loop and a hand-worked example, the clipped surrogate's gradients,
the value loss, the fixed-std policy, and the learner's skip / checkpoint behaviour."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal

from workers.learners.ppo import PPOConfig, PPOLearner, Rollout
from workers.losses.ppo import action_bound_loss, compute_gae, normalize_advantages, ppo_loss
from workers.models.actor_critic import ActorCritic

SMALL = dict(policy_hidden=(16, 16), value_hidden=(16, 16), action_std=0.3, optimizer="adam", policy_lr=1e-3)


def loop_gae(rewards, values, dones, bootstrap, gamma, lam, truncations=None, next_values=None):
    """The textbook recursion, one environment and one step at a time."""
    steps, envs = rewards.shape
    adv = np.zeros((steps, envs))
    for b in range(envs):
        following_adv = 0.0
        for t in reversed(range(steps)):
            cut = truncations is not None and truncations[t, b]
            if cut:
                next_v, following_adv = next_values[t, b], 0.0
            elif dones[t, b]:
                next_v, following_adv = 0.0, 0.0
            else:
                next_v = values[t + 1, b] if t + 1 < steps else bootstrap[b]
            delta = rewards[t, b] + gamma * next_v - values[t, b]
            adv[t, b] = following_adv = delta + gamma * lam * following_adv
    return adv, adv + values


# GAE ---------------------------------------------------------------------------


def test_gae_hand_worked_three_steps():
    # γ = λ = 0.5, one environment; the episode ends (terminally) after step 1.
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    dones = torch.tensor([[0.0], [1.0], [0.0]])
    bootstrap = torch.tensor([2.0])
    adv, ret = compute_gae(rewards, values, dones, bootstrap, gamma=0.5, lam=0.5)
    # t=2: δ = 3 + 0.5·2.0 − 1.5 = 2.5;               A = 2.5
    # t=1: δ = 2 + 0 (terminal) − 1.0 = 1.0;          A = 1.0 (nothing carried across the end)
    # t=0: δ = 1 + 0.5·1.0 − 0.5 = 1.0;               A = 1.0 + 0.25·1.0 = 1.25
    torch.testing.assert_close(adv[:, 0], torch.tensor([1.25, 1.0, 2.5]))
    torch.testing.assert_close(ret[:, 0], torch.tensor([1.75, 2.0, 4.0]))  # A + V

    # The same end as a truncation, with V of the state reached after step 1 equal to 4.0:
    # t=1: δ = 2 + 0.5·4.0 − 1.0 = 3.0;  A = 3.0;   t=0: A = 1.0 + 0.25·3.0 = 1.75
    next_values = torch.tensor([[0.0], [4.0], [0.0]])  # read only where truncated
    adv, ret = compute_gae(
        rewards, values, dones, bootstrap, 0.5, 0.5, truncations=dones.clone(), next_values=next_values
    )
    torch.testing.assert_close(adv[:, 0], torch.tensor([1.75, 3.0, 2.5]))
    torch.testing.assert_close(ret[:, 0], torch.tensor([2.25, 4.0, 4.0]))


@pytest.mark.parametrize("with_truncation", [False, True])
def test_gae_matches_plain_loop(with_truncation):
    rng = np.random.default_rng(0)
    steps, envs, gamma, lam = 40, 6, 0.97, 0.9
    rewards = rng.normal(size=(steps, envs))
    values = rng.normal(size=(steps, envs))
    dones = rng.random((steps, envs)) < 0.12  # several episodes end mid-sequence
    dones[steps - 1, 0] = True  # and one at the very end
    bootstrap = rng.normal(size=envs)
    truncations = (dones & (rng.random((steps, envs)) < 0.5)) if with_truncation else None
    next_values = rng.normal(size=(steps, envs)) if with_truncation else None
    assert dones.sum() >= 10

    expected_adv, expected_ret = loop_gae(rewards, values, dones, bootstrap, gamma, lam, truncations, next_values)

    def t(x):
        return None if x is None else torch.as_tensor(x, dtype=torch.float64)

    args = (t(rewards), t(values), t(dones), t(bootstrap), gamma, lam)
    adv, ret = compute_gae(*args, truncations=t(truncations), next_values=t(next_values))
    np.testing.assert_allclose(adv.numpy(), expected_adv, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ret.numpy(), expected_ret, rtol=1e-12, atol=1e-12)


def test_gae_truncation_needs_next_values():
    z = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="next_values"):
        compute_gae(z, z, z, torch.zeros(2), 0.9, 0.9, truncations=z)


# The PPO loss -------------------------------------------------------------------


def test_clipped_surrogate_gradient_is_zero_outside_the_clip_range():
    eps = 0.2
    # ratio:            1.5    0.5    1.1    0.5    1.5    1.0
    # advantage:        +1     −1     +1     +1     −1     +2
    # clipped?          yes    yes    no     no     no     no
    ratio = torch.tensor([1.5, 0.5, 1.1, 0.5, 1.5, 1.0], dtype=torch.float64)
    adv = torch.tensor([1.0, -1.0, 1.0, 1.0, -1.0, 2.0], dtype=torch.float64)
    old = torch.full((6,), -1.3, dtype=torch.float64)
    new = (old + ratio.log()).requires_grad_()
    zeros = torch.zeros(6, dtype=torch.float64)
    total, terms = ppo_loss(new, old, adv, zeros, zeros, clip=eps, normalize=False)
    (grad,) = torch.autograd.grad(total, new)
    # Where the unclipped term is chosen, d/d log π of −mean(ρ A) is −ρ A / N.
    expected = torch.tensor([0.0, 0.0, -1.1, -0.5, 1.5, -2.0], dtype=torch.float64) / 6
    torch.testing.assert_close(grad, expected)
    assert grad[0] == 0.0 and grad[1] == 0.0  # exactly zero, not merely small
    # −mean(min(ρA, clip(ρ)A)) = −(1.2 − 0.8 + 1.1 + 0.5 − 1.5 + 2.0) / 6 = −2.5 / 6
    assert float(terms["policy"]) == pytest.approx(-2.5 / 6)
    assert float(terms["clip_fraction"]) == pytest.approx(4 / 6)  # |ρ − 1| > 0.2 for 1.5, 0.5, 0.5, 1.5


def test_value_loss_known_answer():
    values = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    returns = torch.tensor([0.0, 2.0, 5.0])
    lp = torch.zeros(3)
    adv = torch.tensor([1.0, -2.0, 0.5])
    total, terms = ppo_loss(lp, lp, adv, values, returns, clip=0.2, value_coef=2.0)
    # ½ mean((1−0)², (2−2)², (3−5)²) = ½ · 5/3
    assert float(terms["value"]) == pytest.approx(5 / 6)
    # At ratio 1 the policy term is −mean(Â) = 0 for normalised advantages, so total = 2 · value.
    assert float(terms["policy"]) == pytest.approx(0.0, abs=1e-7)
    assert float(total.detach()) == pytest.approx(2 * 5 / 6, abs=1e-6)
    (grad,) = torch.autograd.grad(total, values)
    torch.testing.assert_close(grad, 2.0 * (values - returns).detach() / 3)

    # Clipped at 0.5 around old values (1.5, 2, 2): V_clip = (1.0, 2.0, 2.5), errors² (1, 0, 6.25);
    # the larger of clipped and unclipped per sample is (1, 0, 6.25): ½ · 7.25 / 3.
    old_values = torch.tensor([1.5, 2.0, 2.0])
    _, terms = ppo_loss(lp, lp, adv, values, returns, clip=0.2, value_clip=0.5, old_values=old_values)
    assert float(terms["value"]) == pytest.approx(7.25 / 6)


def test_normalised_advantages_have_mean_zero_and_unit_std():
    adv = torch.randn(1000, generator=torch.Generator().manual_seed(0)) * 7.0 + 3.0
    normed = normalize_advantages(adv)
    assert float(normed.mean()) == pytest.approx(0.0, abs=1e-6)
    assert float(normed.std(unbiased=False)) == pytest.approx(1.0, abs=1e-6)
    torch.testing.assert_close(normalize_advantages(torch.tensor([4.0])), torch.tensor([0.0]))


def test_approx_kl_is_zero_at_ratio_one_and_positive_elsewhere():
    lp = torch.randn(50)
    z = torch.zeros(50)
    _, terms = ppo_loss(lp, lp, torch.randn(50), z, z, clip=0.2)
    assert float(terms["approx_kl"]) == 0.0 and float(terms["clip_fraction"]) == 0.0
    _, terms = ppo_loss(lp + 0.3 * torch.randn(50), lp, torch.randn(50), z, z, clip=0.2)
    assert float(terms["approx_kl"]) > 0.0


def test_entropy_bonus_and_action_bound():
    lp, z = torch.zeros(4), torch.zeros(4)
    ent = torch.full((4,), 1.5)
    total, terms = ppo_loss(lp, lp, torch.ones(4), z, z, clip=0.2, entropy=ent, entropy_coef=0.1, normalize=False)
    assert float(total) == pytest.approx(-1.0 - 0.15)  # policy −mean(A) = −1, minus 0.1 · 1.5
    assert float(terms["entropy"]) == pytest.approx(1.5)
    # Means (0.5, −1.5) and (2.0, 0.0) with bound 1: excess (0, 0.5), (1.0, 0) -> (0.25 + 1.0) / 2
    mean = torch.tensor([[0.5, -1.5], [2.0, 0.0]])
    assert float(action_bound_loss(mean, 1.0)) == pytest.approx(0.625)


# The fixed-std policy ------------------------------------------------------------


def test_actor_critic_gaussian_with_fixed_std():
    torch.manual_seed(0)
    net = ActorCritic(5, 3, action_std=[0.1, 0.2, 0.3], policy_hidden=(8,), value_hidden=(8,))
    assert "action_std" not in dict(net.named_parameters())  # not learned
    obs = torch.randn(7, 5)
    action = torch.randn(7, 3)
    mean = net.mean(obs).detach()
    std = torch.tensor([0.1, 0.2, 0.3])
    expected = Normal(mean, std).log_prob(action).sum(-1)
    torch.testing.assert_close(net.log_prob(obs, action), expected)
    torch.testing.assert_close(net.entropy(), Normal(torch.zeros(3), std).entropy().sum())
    assert net.value(obs).shape == (7,)
    assert float(mean.abs().max()) < 0.1  # small output layer at initialisation

    a_det, lp_det = net.act(obs, deterministic=True)
    torch.testing.assert_close(a_det, mean)
    a1, lp1 = net.act(obs, generator=torch.Generator().manual_seed(3))
    a2, lp2 = net.act(obs, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a1, a2)
    torch.testing.assert_close(lp1, net.log_prob(obs, a1).detach())
    assert not torch.equal(a1, a_det)


# The learner ---------------------------------------------------------------------


def make_rollout(seed: int, steps: int = 16, envs: int = 8, obs_dim: int = 3, act_dim: int = 2) -> Rollout:
    rng = np.random.default_rng(seed)
    dones = rng.random((steps, envs)) < 0.1
    return Rollout(
        obs=rng.normal(size=(steps, envs, obs_dim)).astype(np.float32),
        actions=rng.normal(scale=0.3, size=(steps, envs, act_dim)).astype(np.float32),
        log_probs=rng.normal(size=(steps, envs)).astype(np.float32) - 1.0,
        rewards=rng.random((steps, envs)).astype(np.float32),
        dones=dones,
        last_obs=rng.normal(size=(envs, obs_dim)).astype(np.float32),
        truncated=dones & (rng.random((steps, envs)) < 0.5),
        final_obs=rng.normal(size=(steps, envs, obs_dim)).astype(np.float32),
    )


def test_defaults_are_amps_table_4():
    cfg = PPOConfig()
    assert (cfg.clip, cfg.gamma, cfg.lam, cfg.minibatch_size) == (0.02, 0.95, 0.95, 256)
    assert (cfg.policy_lr, cfg.value_lr, cfg.momentum, cfg.optimizer) == (2e-6, 1e-4, 0.9, "sgd")
    assert cfg.policy_hidden == cfg.value_hidden == (1024, 512) and cfg.activation == "relu"
    learner = PPOLearner(6, 2)
    assert isinstance(learner.optimizer, torch.optim.SGD)
    assert [g["lr"] for g in learner.optimizer.param_groups] == [2e-6, 1e-4]


def test_train_on_rollout_runs_epochs_times_minibatches():
    learner = PPOLearner(3, 2, PPOConfig(**SMALL, epochs=3, minibatch_size=48))
    before = copy.deepcopy(learner.module.state_dict())
    metrics = learner.train_on_rollout(make_rollout(0))  # 128 samples: minibatches of 48, 48, 32
    assert learner.version == 3 * 3
    for key in ("policy", "value", "clip_fraction", "approx_kl", "loss", "grad_norm", "explained_variance"):
        assert math.isfinite(metrics[key]), key
    after = learner.module.state_dict()
    assert not torch.equal(before["policy.0.weight"], after["policy.0.weight"])
    assert float(after["obs_norm.count"]) == 128  # the normaliser saw the rollout, after the updates

    actions, log_probs, values = learner.act(np.zeros((5, 3), dtype=np.float32))
    assert actions.shape == (5, 2) and log_probs.shape == (5,) and values.shape == (5,)
    assert actions.dtype == np.float32


def test_missing_values_are_recomputed_with_the_current_weights():
    learner_a = PPOLearner(3, 2, PPOConfig(**SMALL))
    learner_b = PPOLearner(3, 2, PPOConfig(**SMALL))
    rollout = make_rollout(1)
    with torch.no_grad():
        values = learner_a.module.value(torch.as_tensor(rollout.obs)).numpy()
    metrics_a = learner_a.train_on_rollout(rollout)
    metrics_b = learner_b.train_on_rollout(Rollout(**{**vars(rollout), "values": values}))
    assert metrics_a == metrics_b


def test_truncated_needs_final_obs():
    learner = PPOLearner(3, 2, PPOConfig(**SMALL))
    with pytest.raises(ValueError, match="final_obs"):
        learner.train_on_rollout(Rollout(**{**vars(make_rollout(0)), "final_obs": None}))


def test_non_finite_rewards_skip_the_update():
    learner = PPOLearner(3, 2, PPOConfig(**SMALL))
    learner.train_on_rollout(make_rollout(0))
    before = copy.deepcopy(learner.module.state_dict())
    version = learner.version
    bad = make_rollout(1)
    bad.rewards[3, 2] = np.nan
    bad.rewards[5, 1] = np.inf
    metrics = learner.train_on_rollout(bad)
    assert metrics["skipped_updates"] == 1.0 and learner.skipped_updates == 1
    assert learner.version == version
    for k, v in learner.module.state_dict().items():
        assert torch.equal(v, before[k]), k  # weights and normaliser statistics untouched
    weights = learner.get_weights()
    assert weights.version == version
    assert all(bool(torch.isfinite(v).all()) for v in weights.state.values() if v.is_floating_point())
    assert math.isfinite(learner.train_on_rollout(make_rollout(2))["loss"])  # and it carries on


def test_state_dict_round_trip_gives_the_same_next_update():
    first = PPOLearner(3, 2, PPOConfig(**SMALL, epochs=2, minibatch_size=32, seed=0))
    first.train_on_rollout(make_rollout(0))
    first.act(np.zeros((4, 3), dtype=np.float32))  # advance the sampling generator too
    second = PPOLearner(3, 2, PPOConfig(**SMALL, epochs=2, minibatch_size=32, seed=7))
    second.load_state_dict(copy.deepcopy(first.state_dict()))

    rollout = make_rollout(1)
    assert first.train_on_rollout(rollout) == second.train_on_rollout(rollout)
    for k, v in first.module.state_dict().items():
        torch.testing.assert_close(v, second.module.state_dict()[k], rtol=0, atol=0)
    obs = np.ones((4, 3), dtype=np.float32)
    for x, y in zip(first.act(obs), second.act(obs), strict=True):
        np.testing.assert_array_equal(x, y)
    assert first.version == second.version


# PhysicsVAE's helper branch as PPO trains it -------------------------------------------------------------


def helper_module(seed: int = 0):
    from workers.learners.ppo import build_actor_critic
    from workers.models.actor_critic import HelperLayout

    layout = HelperLayout(state_dim=5, goal_dim=2, latent_dim=3, action_dim=4, hidden=(8,))
    torch.manual_seed(seed)
    cfg = PPOConfig(**{**SMALL, "policy_out_scale": 1.0})
    module = build_actor_critic(layout.obs_dim, layout.act_dim, cfg, layout)
    module.obs_norm.update(torch.randn(64, layout.obs_dim) * 2 + 0.5)
    return module, layout


def test_the_helper_reads_the_latent_not_the_goal_and_its_density_factorises():
    """π(u_z, u_h | s, g, b) = N(u_z; μ_g(s, g), σ²) · N(u_h; H(s, b + u_z), σ²), worked from the two
    networks by hand; H's mean moves with b and u_z and not with the goal; μ_g's not with b."""
    module, lay = helper_module()
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(6, lay.obs_dim, generator=g)
    action = torch.randn(6, lay.act_dim, generator=g)
    n = module.obs_norm(obs)
    s_norm = n[:, : lay.state_dim]
    mu_z = module.policy["latent"](n[:, : lay.state_dim + lay.goal_dim])
    z = obs[:, lay.state_dim + lay.goal_dim :] + action[:, : lay.latent_dim]
    mu_h = module.policy["helper"](torch.cat((s_norm, z), -1))
    by_hand = Normal(mu_z, 0.3).log_prob(action[:, : lay.latent_dim]).sum(-1)
    by_hand = by_hand + Normal(mu_h, 0.3).log_prob(action[:, lay.latent_dim :]).sum(-1)
    torch.testing.assert_close(module.log_prob(obs, action), by_hand)

    other_goal, other_b = obs.clone(), obs.clone()
    other_goal[:, lay.state_dim : lay.state_dim + lay.goal_dim] += 1.0
    other_b[:, lay.state_dim + lay.goal_dim :] += 1.0
    helper = slice(lay.latent_dim, None)
    # The goal moves only the obs normaliser's input of μ_g: H(s, z) with the same u_z does not move.
    torch.testing.assert_close(module.mean(other_goal, action)[:, helper], module.mean(obs, action)[:, helper])
    assert (module.mean(other_goal, action)[:, : lay.latent_dim] - mu_z).abs().max() > 1e-3
    assert (module.mean(other_b, action)[:, helper] - mu_h).abs().max() > 1e-3
    torch.testing.assert_close(module.mean(other_b, action)[:, : lay.latent_dim], mu_z)


def test_the_helpers_sampled_log_prob_is_its_density_at_the_sample():
    module, lay = helper_module()
    obs = torch.randn(200, lay.obs_dim, generator=torch.Generator().manual_seed(2))
    action, log_prob = module.act(obs, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(log_prob, module.log_prob(obs, action), atol=1e-4, rtol=1e-5)
    # H's mean is taken at the sampled latent: the helper's noise is what is left after it.
    with torch.no_grad():
        resid = (action - module.mean(obs, action)) / 0.3
    assert abs(float(resid.mean())) < 0.05 and abs(float(resid.std()) - 1.0) < 0.05
    det, _ = module.act(obs, deterministic=True)
    torch.testing.assert_close(det, module.mean(obs))


def test_ppo_with_the_helper_learns_an_action_that_depends_on_the_latent():
    """A one-step problem whose best helper output is a function of the sampled latent: reward
    −‖u_h − (b + u_z)[:A]‖² with A = latent size. Only a policy whose helper reads z can earn more than the
    noise allows; PPO with the helper lowers the error over a few iterations."""
    from workers.learners.ppo import build_actor_critic
    from workers.models.actor_critic import HelperLayout

    lay = HelperLayout(state_dim=2, goal_dim=1, latent_dim=2, action_dim=2, hidden=(32,))
    cfg = PPOConfig(
        policy_hidden=(32,), value_hidden=(32,), action_std=0.3, optimizer="adam", policy_lr=3e-3, value_lr=3e-3,
        clip=0.2, epochs=4, minibatch_size=128, seed=0,
    )  # fmt: skip
    learner = PPOLearner(lay.obs_dim, lay.act_dim, cfg, helper=lay)
    assert isinstance(learner.module, type(build_actor_critic(lay.obs_dim, lay.act_dim, cfg, lay)))
    rng = np.random.default_rng(0)

    def error(obs, act):
        z = obs[:, 3:] + act[:, :2]
        return ((act[:, 2:] - z) ** 2).sum(-1)

    errors = []
    for _ in range(30):
        obs = rng.normal(size=(1, 256, lay.obs_dim)).astype(np.float32)
        act, logp, _ = learner.act(obs[0])
        errors.append(float(error(obs[0], act).mean()))
        rollout = Rollout(
            obs=obs, actions=act[None], log_probs=logp[None], rewards=-error(obs[0], act)[None].astype(np.float32),
            dones=np.ones((1, 256), np.float32), last_obs=obs[0],
        )  # fmt: skip
        learner.train_on_rollout(rollout)
    assert np.mean(errors[-5:]) < 0.5 * np.mean(errors[:5]), errors
