"""AMP discriminator: losses with known answers, the gradient penalty, the learner's safety and checkpoints."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorConfig, DiscriminatorLearner
from workers.losses.discriminator import (
    discriminator_loss,
    gradient_penalty,
    logit_regularization,
    style_reward,
)
from workers.models.discriminator import Discriminator

OBS = 5  # Φ(s) size in these tests; transitions are [B, 10]


def small_config(**overrides) -> DiscriminatorConfig:
    return DiscriminatorConfig(**{"hidden": (16, 16), "lr": 1e-3, **overrides})


def random_batch(seed: int, n: int = 8, shift: float = 1.0) -> DiscriminatorBatch:
    rng = np.random.default_rng(seed)
    return DiscriminatorBatch(
        data_obs=rng.normal(0.0, 1.0, (n, 2 * OBS)).astype(np.float32),
        policy_obs=rng.normal(shift, 1.0, (n, 2 * OBS)).astype(np.float32),
    )


def module_state(learner: DiscriminatorLearner) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in learner.module.state_dict().items()}


def assert_same_state(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


# Gradient penalty -------------------------------------------------------------
def test_gradient_penalty_of_a_linear_discriminator():
    # D(x) = w·x with w = (3, 4): ∇_x D = w everywhere, ‖w‖ = 5, ‖w‖² = 25.
    # Penalty = w_gp/2 · 25 = 10/2 · 25 = 125; mean gradient norm 5.
    w = torch.tensor([3.0, 4.0], requires_grad=True)
    x = torch.randn(6, 2, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    penalty, terms = gradient_penalty(x @ w, x, w_gp=10.0)
    assert penalty.item() == pytest.approx(125.0)
    assert terms["input_grad_norm"].item() == pytest.approx(5.0)
    # The penalty is differentiable in the discriminator's parameters: d/dw (w_gp/2 ‖w‖²) = w_gp · w = (30, 40).
    penalty.backward()
    torch.testing.assert_close(w.grad, torch.tensor([30.0, 40.0]))


def test_gradient_penalty_of_a_quadratic_discriminator():
    # D(x) = ½‖x‖²: ∇_x D = x. Rows (1, 2, 2) and (0, 3, 4): ‖x‖ = 3 and 5, ‖x‖² = 9 and 25.
    # Penalty = w_gp/2 · mean(9, 25) = 2/2 · 17 = 17; mean gradient norm (3 + 5)/2 = 4.
    x = torch.tensor([[1.0, 2.0, 2.0], [0.0, 3.0, 4.0]], requires_grad=True)
    penalty, terms = gradient_penalty(0.5 * x.pow(2).sum(-1), x, w_gp=2.0)
    assert penalty.item() == pytest.approx(17.0)
    assert terms["input_grad_norm"].item() == pytest.approx(4.0)
    assert terms["gp"] is penalty


def test_gradient_penalty_needs_inputs_that_require_grad():
    x = torch.ones(3, 2)
    with pytest.raises(ValueError, match="require grad"):
        gradient_penalty(x.sum(-1), x, w_gp=1.0)


def test_gradient_penalty_gradcheck_float64():
    # A tiny tanh net D(x) = v·tanh(W x + b); the penalty is checked against finite
    # differences with respect to the parameters and the inputs.
    gen = torch.Generator().manual_seed(0)
    W = torch.randn(4, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    b = torch.randn(4, dtype=torch.float64, generator=gen, requires_grad=True)
    v = torch.randn(4, dtype=torch.float64, generator=gen, requires_grad=True)
    x = torch.randn(5, 3, dtype=torch.float64, generator=gen, requires_grad=True)

    def penalty(W, b, v, x):
        xi = x if x.requires_grad else x.requires_grad_(True)
        d = torch.tanh(xi @ W.T + b) @ v
        return gradient_penalty(d, xi, w_gp=3.0)[0]

    assert torch.autograd.gradcheck(penalty, (W, b, v, x))


def test_gradient_penalty_through_the_discriminator_network_gradcheck():
    # The same check through the discriminator's own MLP, on normalised inputs, w.r.t. every parameter.
    torch.manual_seed(0)
    disc = Discriminator(OBS, hidden=(6,), act="tanh").double()
    disc.update_normalizer(torch.randn(32, 2 * OBS, dtype=torch.float64))
    xn = disc.normalize(torch.randn(4, 2 * OBS, dtype=torch.float64)).detach().requires_grad_(True)
    names = [name for name, _ in disc.net.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_(True) for p in disc.net.parameters())

    def penalty(*params):
        d = torch.func.functional_call(disc.net, dict(zip(names, params, strict=True)), (xn,)).squeeze(-1)
        return gradient_penalty(d, xn, w_gp=10.0)[0]

    assert torch.autograd.gradcheck(penalty, params)


# Classification losses and rewards -----------------------------------------------
def test_lsgan_loss_known_values():
    # data D = (1, 0): ((1-1)² + (0-1)²)/2 = 0.5;  policy D = (-1, 1): ((-1+1)² + (1+1)²)/2 = 2.
    total, terms = discriminator_loss(torch.tensor([1.0, 0.0]), torch.tensor([-1.0, 1.0]), "lsgan")
    assert terms["loss_data"].item() == pytest.approx(0.5)
    assert terms["loss_policy"].item() == pytest.approx(2.0)
    assert total.item() == pytest.approx(2.5)  # the sum, as in AMP Eq. 6 (no ½)


def test_bce_loss_known_values():
    # D = log 3 means σ(D) = 3/4. Data: -log(3/4) = 0.287682; policy: -log(1 - 3/4) = log 4 = 1.386294.
    d = torch.tensor([math.log(3.0)])
    total, terms = discriminator_loss(d, d, "bce")
    assert terms["loss_data"].item() == pytest.approx(-math.log(0.75))
    assert terms["loss_policy"].item() == pytest.approx(math.log(4.0))
    assert total.item() == pytest.approx(0.287682 + 1.386294, abs=1e-6)
    # D = 0 on both sides: log 2 each.
    total, _ = discriminator_loss(torch.zeros(3), torch.zeros(2), "bce")
    assert total.item() == pytest.approx(2 * math.log(2.0))


def test_lsgan_style_reward_known_values():
    # max(0, 1 - 0.25 (D - 1)²): D=1 -> 1; D=-1 -> 1 - 0.25·4 = 0; D=3 -> 0; D=0 and D=2 -> 0.75;
    # D=5 -> 1 - 4 = -3 -> 0; D=-3 -> 0.
    d = torch.tensor([1.0, -1.0, 3.0, 0.0, 2.0, 5.0, -3.0], requires_grad=True)
    r, terms = style_reward(d, "lsgan")
    torch.testing.assert_close(r, torch.tensor([1.0, 0.0, 0.0, 0.75, 0.75, 0.0, 0.0]))
    assert not r.requires_grad
    assert terms["style_reward"].item() == pytest.approx(2.5 / 7)


def test_bce_style_reward_known_values():
    # -log(1 - σ(D)): D=0 -> log 2; D=log 3 -> log 4; D=-30 -> ~0; D=30 -> clamped at -log(1e-4) = 9.2103.
    d = torch.tensor([0.0, math.log(3.0), -30.0, 30.0])
    r, _ = style_reward(d, "bce")
    torch.testing.assert_close(r, torch.tensor([math.log(2.0), math.log(4.0), 0.0, -math.log(1e-4)]))


def test_logit_regularization_known_value():
    # 0.5 · (1² + 2² + 2²) = 4.5
    total, terms = logit_regularization(torch.tensor([[1.0, 2.0, -2.0]]), 0.5)
    assert total.item() == pytest.approx(4.5) and terms["logit_reg"] is total


def test_unknown_loss_type_raises_naming_it():
    d = torch.zeros(2)
    with pytest.raises(ValueError, match="wgan"):
        discriminator_loss(d, d, "wgan")
    with pytest.raises(ValueError, match="wgan"):
        style_reward(d, "wgan")
    with pytest.raises(ValueError, match="wgan"):
        DiscriminatorConfig(loss="wgan")
    with pytest.raises(ValueError, match="policy_only"):
        DiscriminatorConfig(gp_on="policy_only")


# The network ----------------------------------------------------------------------
def test_discriminator_shapes_and_skill_conditioning():
    torch.manual_seed(0)
    x = torch.randn(6, 2 * OBS)
    plain = Discriminator(OBS, hidden=(8,))
    assert plain(x).shape == (6,)
    with pytest.raises(ValueError, match="not skill-conditioned"):
        plain(x, torch.zeros(6, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\[B, 10\]"):
        plain(torch.randn(6, OBS))
    for embed in (0, 4):
        disc = Discriminator(OBS, hidden=(8,), num_skills=3, skill_embed_dim=embed)
        with pytest.raises(ValueError, match="skill labels"):
            disc(x)
        d0, d2 = disc(x, torch.zeros(6, dtype=torch.long)), disc(x, torch.full((6,), 2))
        assert d0.shape == (6,) and not torch.allclose(d0, d2)


def test_normalizer_is_shared_by_both_states():
    disc = Discriminator(OBS, hidden=(8,))
    # First state all 1, second all 3: per-feature mean 2 and std 1 over the 2·4 states.
    obs = torch.cat((torch.ones(4, OBS), torch.full((4, OBS), 3.0)), dim=-1)
    disc.update_normalizer(obs)
    torch.testing.assert_close(disc.normalizer.mean, torch.full((OBS,), 2.0, dtype=torch.float64))
    expected = torch.cat((-torch.ones(4, OBS), torch.ones(4, OBS)), dim=-1)
    torch.testing.assert_close(disc.normalize(obs), expected)


# The learner ----------------------------------------------------------------------
def test_penalising_policy_samples_adds_to_the_penalty():
    batch = random_batch(0)
    data_only = DiscriminatorLearner(OBS, small_config(gp_on="data"), seed=1)
    both = DiscriminatorLearner(OBS, small_config(gp_on="data_and_policy"), seed=1)
    t_data = data_only.evaluate(batch)
    t_both = both.evaluate(batch)
    # Same seed, same weights: the data part is identical and the policy part is added on top.
    assert t_both["gp_data"] == pytest.approx(t_data["gp_data"])
    assert t_both["gp_policy"] > 0 and t_both["input_grad_norm_policy"] > 0
    assert t_both["gp"] == pytest.approx(t_data["gp"] + t_both["gp_policy"])
    assert t_both["gp"] > t_data["gp"]


def test_the_learners_penalty_is_taken_on_the_data_side_by_hand():
    """gp_data is (w_gp/2)·E‖∇D‖² at the data samples, computed here by autograd on the module directly:
    a learner that penalised the policy samples instead (or took the batch's other side) fails this."""
    batch = random_batch(0, shift=3.0)
    for features in ("normalised", "raw"):
        learner = DiscriminatorLearner(OBS, small_config(gp_features=features), seed=1)
        learner.module.update_normalizer(torch.from_numpy(batch.data_obs) * 4.0)  # std far from 1
        terms = learner.evaluate(batch)

        def by_hand(obs: np.ndarray, features: str = features, learner: DiscriminatorLearner = learner) -> float:
            raw = torch.from_numpy(obs).requires_grad_(True)
            normalised = learner.module.normalize(raw).detach().requires_grad_(True)
            x = raw if features == "raw" else normalised
            d = learner.module.logits(learner.module.normalize(raw) if features == "raw" else normalised)
            (grad,) = torch.autograd.grad(d.sum(), x)
            return float(0.5 * 10.0 * grad.pow(2).sum(-1).mean())

        assert terms["gp_data"] == pytest.approx(by_hand(batch.data_obs), rel=1e-5)
        assert terms["gp_data"] != pytest.approx(by_hand(batch.policy_obs), rel=1e-2)


def test_raw_feature_penalty_is_the_normalised_one_over_the_variance():
    """Chain rule: with φ_n = (φ − μ)/s, ∇_φ D = ∇_{φ_n} D / s. With s = 2 on every feature (data at ±2),
    the raw penalty is a quarter of the normalised one (AMP's Eq. 8 is on the raw Φ)."""
    data = np.concatenate([np.full((4, 2 * OBS), 2.0), np.full((4, 2 * OBS), -2.0)]).astype(np.float32)
    batch = DiscriminatorBatch(data, data + 1.0)
    gp = {}
    for features in ("normalised", "raw"):
        learner = DiscriminatorLearner(OBS, small_config(gp_features=features), seed=1)
        learner.module.update_normalizer(torch.from_numpy(data))
        torch.testing.assert_close(learner.module.normalizer.std, torch.full((OBS,), 2.0, dtype=torch.float64))
        gp[features] = learner.evaluate(batch)["gp_data"]
    assert gp["raw"] == pytest.approx(gp["normalised"] / 4, rel=1e-5)
    with pytest.raises(ValueError, match="gp_features: unknown"):
        DiscriminatorConfig(gp_features="whitened")


def test_table_4s_sgd_with_momentum_is_the_optimiser_when_asked():
    sgd = DiscriminatorLearner(OBS, small_config(optimizer="sgd", lr=1e-5, momentum=0.9), seed=0)
    assert isinstance(sgd.optimizer, torch.optim.SGD)
    assert sgd.optimizer.param_groups[0]["momentum"] == 0.9 and sgd.optimizer.param_groups[0]["lr"] == 1e-5
    assert isinstance(DiscriminatorLearner(OBS, small_config(), seed=0).optimizer, torch.optim.Adam)
    with pytest.raises(ValueError, match="optimizer: unknown"):
        DiscriminatorConfig(optimizer="lbfgs")


def test_update_reports_metrics_and_learns_a_separable_toy():
    learner = DiscriminatorLearner(OBS, small_config(replay_mix=0.5), seed=0)
    for i in range(150):
        metrics = learner.update(random_batch(i, n=32, shift=2.0))
    for key in ("loss", "loss_data", "loss_policy", "gp", "gp_data", "input_grad_norm_data", "grad_norm", "lr"):
        assert math.isfinite(metrics[key]), key
    assert metrics["accuracy"] > 0.9 and metrics["d_data"] > 0 > metrics["d_policy"]
    assert learner.version == 150 and metrics["replay_size"] == 150 * 32
    test = random_batch(10_000, n=64, shift=2.0)
    r_data, r_policy = learner.reward(test.data_obs), learner.reward(test.policy_obs)
    assert r_data.shape == (64,) and r_data.dtype == np.float32
    assert ((0 <= r_policy) & (r_policy <= 1)).all() and r_data.mean() > r_policy.mean() + 0.3
    np.testing.assert_allclose(r_data, style_reward(torch.from_numpy(learner.logits(test.data_obs)))[0].numpy())


def test_replay_is_a_ring_and_mixes_past_transitions():
    learner = DiscriminatorLearner(OBS, small_config(replay_capacity=10, replay_mix=1.0), seed=0)
    sizes = []
    for i in range(4):
        batch = DiscriminatorBatch(np.zeros((4, 2 * OBS), np.float32), np.full((4, 2 * OBS), float(i), np.float32))
        mixed = learner._mix_replay(batch)
        # The first batch meets an empty replay and is used as is; later ones are replaced by past batches.
        values = set(np.unique(np.asarray(mixed.policy_obs)))
        assert values == {0.0} if i == 0 else values <= set(map(float, range(i)))
        sizes.append(len(learner.replay))
    assert sizes == [4, 8, 10, 10]
    # Ring order: the oldest rows (batch 0) were overwritten by batch 3 first.
    assert sorted(np.unique(learner.replay.obs[:, 0])) == [1.0, 2.0, 3.0]


def test_skill_conditioned_learner_needs_labels_and_replays_them():
    learner = DiscriminatorLearner(OBS, small_config(num_skills=2, replay_mix=0.5), seed=0)
    batch = random_batch(0)
    with pytest.raises(ValueError, match="skill"):
        learner.update(batch)
    labelled = DiscriminatorBatch(batch.data_obs, batch.policy_obs, np.zeros(8, int), np.ones(8, int))
    learner.update(labelled)
    metrics = learner.update(labelled)
    assert math.isfinite(metrics["loss"]) and (learner.replay.skill[: len(learner.replay)] == 1).all()
    assert learner.reward(batch.data_obs, np.zeros(8, int)).shape == (8,)


@pytest.mark.parametrize("side", ["data_obs", "policy_obs"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_batch_is_skipped(side, bad):
    learner = DiscriminatorLearner(OBS, small_config(), seed=0)
    learner.update(random_batch(0))
    before, version, replay = module_state(learner), learner.version, len(learner.replay)
    published = learner.get_weights()
    batch = random_batch(1)
    getattr(batch, side)[3, 2] = bad
    metrics = learner.update(batch)
    assert metrics["skipped_updates"] == 1 and learner.skipped_updates == 1
    assert learner.version == version and len(learner.replay) == replay
    assert_same_state(module_state(learner), before)  # normaliser statistics included
    weights = learner.get_weights()
    assert weights is published and all(torch.isfinite(v).all() for v in weights.state.values())
    # The next good batch updates as usual.
    assert "grad_norm" in learner.update(random_batch(2)) and learner.version == version + 1


def test_state_dict_round_trip_restores_the_optimizer():
    config = small_config(replay_mix=0.0)  # the replay is not in the state dict
    a = DiscriminatorLearner(OBS, config, seed=0)
    for i in range(3):
        a.update(random_batch(i))
    b = DiscriminatorLearner(OBS, config, seed=7)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    assert b.version == 3
    # A copy with the same network but a fresh optimiser takes a different next step.
    c = DiscriminatorLearner(OBS, config, seed=7)
    c.module.load_state_dict(a.module.state_dict())
    batch = random_batch(3)
    ma, mb, _ = a.update(batch), b.update(batch), c.update(batch)
    assert ma.pop("replay_size") != mb.pop("replay_size") and ma == mb
    assert_same_state(module_state(a), module_state(b))
    assert not torch.equal(a.module.net[0].weight, c.module.net[0].weight)


def test_same_seed_same_learner():
    a, b = (DiscriminatorLearner(OBS, small_config(), seed=3) for _ in range(2))
    for i in range(3):
        assert a.update(random_batch(i)) == b.update(random_batch(i))
    assert_same_state(module_state(a), module_state(b))


def test_amps_reward_mix_by_hand_with_its_named_terms():
    from workers.learners.discriminator import amp_reward

    style = np.array([[0.2, 1.0], [0.0, 0.5]], np.float32)
    task = np.array([[1.0, 0.0], [0.5, 0.5]], np.float32)
    total, terms = amp_reward(style, task, task_weight=0.5, style_weight=0.5)  # AMP Eq. 4, w_G = w_S = 0.5
    np.testing.assert_allclose(total, [[0.6, 0.5], [0.25, 0.5]], rtol=1e-6)
    assert total.dtype == np.float32 and set(terms) == {"style", "task", "total"}
    np.testing.assert_array_equal(terms["style"], style)
    only_style, terms = amp_reward(style, None, task_weight=0.0, style_weight=1.0)  # imitation only
    np.testing.assert_array_equal(only_style, style)
    np.testing.assert_array_equal(terms["task"], np.zeros_like(style))
