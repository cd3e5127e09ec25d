"""Known answers for the VAE controller: KLs, the priors' posteriors, the losses, the mixture of experts."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal, kl_divergence

from workers.learners.base import Schedule, Weights
from workers.learners.vae import ControlVAEObjective, VAEBatch, VAEConfig, VAELearner, vae_config
from workers.losses.kl import gaussian_kl, latent_usage
from workers.losses.vae import controlvae_loss, discounts, physicsvae_loss, pulse_loss
from workers.models.vae import MixtureOfExperts, VAEController
from workers.models.world_model import WorldModel


def test_gaussian_kl_matches_torch_distributions():
    g = torch.Generator().manual_seed(0)
    mq, mp = torch.randn(5, 7, generator=g), torch.randn(5, 7, generator=g)
    lq, lp = 0.5 * torch.randn(5, 7, generator=g), 0.5 * torch.randn(5, 7, generator=g)
    expected = kl_divergence(Normal(mq, lq.exp()), Normal(mp, lp.exp())).sum(-1)
    torch.testing.assert_close(gaussian_kl(mq, lq, mp, lp), expected)
    # Against the standard normal prior.
    zero = torch.zeros(5, 7)
    expected = kl_divergence(Normal(mq, lq.exp()), Normal(zero, 1.0)).sum(-1)
    torch.testing.assert_close(gaussian_kl(mq, lq, zero, zero), expected)


def test_latent_usage_sees_a_collapsed_dimension():
    """Three latent dimensions over a batch of four: the first carries the input (μ = ±1, σ = 0.1), the second
    is collapsed onto the prior (μ = 0, σ = 1), the third has a constant offset (μ = 0.5, σ = 1). Per dimension,
    KL = −log σ + (σ² + μ²)/2 − ½: 2.3026 + 0.005 + 0.5 − 0.5 = 2.3076; 0; 0.125. Only the first varies."""
    mean = torch.tensor([[1.0, 0.0, 0.5], [-1.0, 0.0, 0.5], [1.0, 0.0, 0.5], [-1.0, 0.0, 0.5]])
    log_std = torch.log(torch.tensor([0.1, 1.0, 1.0])).expand(4, 3)
    usage = latent_usage(mean, log_std)
    torch.testing.assert_close(usage["kl_per_dim"], torch.tensor([2.30759, 0.0, 0.125]), atol=1e-4, rtol=0)
    torch.testing.assert_close(usage["kl"], gaussian_kl(mean, log_std, torch.zeros(3), torch.zeros(3)).mean())
    assert int(usage["active_dims"]) == 1


def test_conditional_prior_kl_is_controlvae_eq11():
    # q = N(μ_p + μ_q, σ_p²), p = N(μ_p, σ_p²): KL = ‖μ_q‖² / (2σ_p²). With μ_q = (0.3, 0.4), σ_p = 0.3:
    # 0.25 / 0.18 = 1.3889.
    mu_p = torch.tensor([[1.0, -2.0]])
    mu_q = torch.tensor([[0.3, 0.4]])
    log_s = torch.full((1, 2), math.log(0.3))
    kl = gaussian_kl(mu_p + mu_q, log_s, mu_p, log_s)
    torch.testing.assert_close(kl, torch.tensor([0.25 / 0.18]))


def test_model_conditional_posterior_kl_equals_residual_norm():
    torch.manual_seed(0)
    vae = VAEController(10, 4, prior="conditional", latent_dim=3, encoder_hidden=(8,), policy="mlp", policy_hidden=(8,))
    s, s2 = torch.randn(6, 10), torch.randn(6, 10)
    q, p = vae.encode(s, s2)
    residual = q.mean - p.mean
    torch.testing.assert_close(gaussian_kl(q.mean, q.log_std, p.mean, p.log_std), (residual**2).sum(-1) / 0.18)


def test_kl_gradcheck_float64():
    g = torch.Generator().manual_seed(1)
    args = [torch.randn(3, 4, generator=g, dtype=torch.float64, requires_grad=True) for _ in range(4)]
    assert torch.autograd.gradcheck(gaussian_kl, args)


def test_prior_kinds():
    torch.manual_seed(0)
    s = torch.randn(4, 10)
    for kind in ("standard_normal", "conditional", "learned"):
        vae = VAEController(10, 4, prior=kind, latent_dim=3, encoder_hidden=(8,), policy="mlp", policy_hidden=(8,))
        p = vae.prior_dist(s)
        if kind == "standard_normal":
            assert torch.equal(p.mean, torch.zeros(4, 3)) and torch.equal(p.log_std, torch.zeros(4, 3))
        elif kind == "conditional":
            torch.testing.assert_close(p.log_std, torch.full((4, 3), math.log(0.3)))
        else:
            assert (p.log_std >= -5).all() and (p.log_std <= 0.5).all()
    with pytest.raises(ValueError, match="unknown prior type 'gaussian'"):
        VAEController(10, 4, prior="gaussian")


def test_mixture_of_experts_blends_parameters():
    # The layer-by-layer output blend must equal running one network whose weights are the gate-weighted
    # sum of the experts' weights, built explicitly per sample.
    torch.manual_seed(0)
    moe = MixtureOfExperts(5, 2, 3, num_experts=3, hidden=(4,), gate_hidden=(6,))
    s, z = torch.randn(2, 5), torch.randn(2, 2)
    out = moe(s, z)
    g = torch.softmax(moe.gate(torch.cat((s, z), -1)), -1)
    for n in range(2):
        h = s[n]
        for i, (w, b, norm) in enumerate(zip(moe.weights, moe.biases, moe.norms, strict=True)):
            w_n = (g[n, :, None, None] * w).sum(0)
            b_n = (g[n, :, None] * b).sum(0)
            h = norm(torch.cat((h, z[n]))) @ w_n + b_n
            if i < len(moe.weights) - 1:
                h = torch.nn.functional.elu(h)
        torch.testing.assert_close(out[n], h)


def test_controlvae_loss_known_answer():
    # Two steps, γ = 0.5: normalised discounts (2/3, 1/3). Rec per step: |1 − 0| · w = 2 and 4,
    # so rec = 2·2/3 + 4·1/3 = 8/3. KL 3 and 6 → 4. Actions (1, −1): w_a1·2 + w_a2·2 = 0.2 + 0.02.
    pred = torch.zeros(1, 2, 1)
    ref = torch.tensor([[[1.0], [2.0]]])
    kl = torch.tensor([[3.0, 6.0]])
    actions = torch.tensor([[[1.0, -1.0], [1.0, -1.0]]])
    total, terms = controlvae_loss(pred, ref, kl, actions, torch.tensor([2.0]), 0.5, 0.1, 0.1, 0.01)
    torch.testing.assert_close(terms["rec"], torch.tensor(8 / 3))
    torch.testing.assert_close(terms["kl"], torch.tensor(4.0))
    torch.testing.assert_close(terms["act"], torch.tensor(0.22))
    torch.testing.assert_close(total, torch.tensor(8 / 3 + 0.4 + 0.22))
    torch.testing.assert_close(discounts(3, 1.0, pred), torch.full((3,), 1 / 3))


def test_physicsvae_alpha_zero_is_behaviour_cloning():
    a, e = torch.ones(2, 1, 3), torch.zeros(2, 1, 3)
    s_pred, s_true = torch.zeros(2, 1, 4), torch.ones(2, 1, 4)
    kl = torch.full((2, 1), 2.0)
    total, terms = physicsvae_loss(a, e, s_pred, s_true, kl, alpha=0.0, beta=2.0, reduction="sum")
    assert float(terms["bc"]) == 3.0 and float(terms["sim"]) == 4.0
    assert float(total) == 3.0 + 2.0 * 2.0
    total_alpha, _ = physicsvae_loss(a, e, s_pred, s_true, kl, alpha=0.5, beta=2.0, reduction="sum")
    assert float(total_alpha) == float(total) + 0.5 * 4.0


def test_physicsvae_default_reduction_is_the_authors_mean_squared_error():
    """Worked by hand: errors (1, 2, 3) on A = 3 actions and (2, 0, 0, 0) on D = 4 features; the KL 0.5
    and 1.5 over two samples. The authors' nn.MSELoss: bc = (1 + 4 + 9) / 3, sim = 4 / 4; the KL stays
    summed over the latent and averaged over the batch: 1.0."""
    a = torch.tensor([[[1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0]]])
    e = torch.zeros(2, 1, 3)
    s_pred, s_true = torch.tensor([[[2.0, 0, 0, 0]], [[2.0, 0, 0, 0]]]), torch.zeros(2, 1, 4)
    kl = torch.tensor([[0.5], [1.5]])
    total, terms = physicsvae_loss(a, e, s_pred, s_true, kl, alpha=1e-4, beta=2.0)
    torch.testing.assert_close(terms["bc"], torch.tensor(14 / 3))
    torch.testing.assert_close(terms["sim"], torch.tensor(1.0))
    torch.testing.assert_close(terms["kl"], torch.tensor(1.0))
    torch.testing.assert_close(total, torch.tensor(14 / 3 + 1e-4 + 2.0))
    # the same batch as Eq. 1 is printed: sums over the dimensions
    total_sum, terms_sum = physicsvae_loss(a, e, s_pred, s_true, kl, alpha=1e-4, beta=2.0, reduction="sum")
    torch.testing.assert_close(terms_sum["bc"], torch.tensor(14.0))
    torch.testing.assert_close(terms_sum["sim"], torch.tensor(4.0))
    torch.testing.assert_close(total_sum, torch.tensor(14.0 + 4e-4 + 2.0))
    with pytest.raises(ValueError, match="reduction"):
        physicsvae_loss(a, e, s_pred, s_true, kl, alpha=1e-4, beta=2.0, reduction="max")


def test_the_physicsvae_learner_uses_the_configured_reduction(walk_run):
    """One batch, one seed, two learners: the mean reduction's bc and sim terms are the sum's divided by
    A = 28 and D = 15·16 + 3 = 243, the KL is the same, and an unknown reduction names its key."""
    terms = {}
    for reduction in ("mean", "sum"):
        torch.manual_seed(0)
        learner = small_learner("physicsvae", "standard_normal", physicsvae_reduction=reduction)
        batch = random_batch(walk_run)
        learner.before_update(batch)
        with torch.no_grad():
            _, terms[reduction] = learner.loss(batch)
    torch.testing.assert_close(terms["mean"]["bc"] * 28, terms["sum"]["bc"])
    torch.testing.assert_close(terms["mean"]["sim"] * 243, terms["sum"]["sim"])
    torch.testing.assert_close(terms["mean"]["kl"], terms["sum"]["kl"])
    assert float(terms["mean"]["sim"]) > 0
    with pytest.raises(ValueError, match="vae.physicsvae_reduction"):
        vae_config(objective="physicsvae", prior="standard_normal", physicsvae_reduction="max")


def test_the_plain_network_is_physicsvaes_table_2():
    """network=plain: ReLU MLPs taking their inputs once (encoder 2D -> 256 -> 128, decoder D + Z -> 512 x 3),
    no layer norm; concat (ours) re-concatenates the conditioning at every layer."""
    from workers.learners.vae import build_controller

    d, z = 15 * 16 + 3, 32
    cfg = vae_config(objective="physicsvae", prior="standard_normal", latent_dim=z, encoder_hidden=(256, 128),
                    policy="mlp", policy_hidden=(512, 512, 512), activation="relu", network="plain")  # fmt: skip
    vae = build_controller(15, 28, cfg)
    linears = [m for m in vae.posterior.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(2 * d, 256), (256, 128), (128, 2 * z)]
    linears = [m for m in vae.policy.modules() if isinstance(m, torch.nn.Linear)]
    assert [m.in_features for m in linears] == [d + z, 512, 512, 512] and linears[-1].out_features == 28
    assert not any(isinstance(m, (torch.nn.LayerNorm, torch.nn.ELU)) for m in vae.modules())
    assert any(isinstance(m, torch.nn.ReLU) for m in vae.modules())
    ours = build_controller(15, 28, vae_config(objective="physicsvae", prior="standard_normal", latent_dim=z,
                                              policy="mlp", policy_hidden=(512,)))  # fmt: skip
    assert any(isinstance(m, torch.nn.LayerNorm) for m in ours.policy.modules())
    s = torch.randn(4, d)
    q, p = vae.encode(s, s + 0.1)
    assert q.mean.shape == (4, z) and vae.act(s, q.mean).shape == (4, 28)
    with pytest.raises(ValueError, match="vae.network"):
        VAEConfig(network="resnet")


def test_pulse_regularises_consecutive_latents():
    means = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [1.0, 2.0]]])  # steps of squared length 1 and 4: mean 2.5
    zero = torch.zeros(1, 3, 4)
    total, terms = pulse_loss(zero, zero, means, torch.zeros(1, 3), lambda_regu=0.1, beta=1.0)
    assert float(terms["regu"]) == 2.5
    assert float(total) == pytest.approx(0.25)


def small_learner(objective: str = "controlvae", prior: str = "conditional", **kw) -> VAELearner:
    cfg = vae_config(
        objective=objective,
        prior=prior,
        latent_dim=4,
        encoder_hidden=(16,),
        policy="moe",
        num_experts=2,
        policy_hidden=(16,),
        gate_hidden=(8,),
        lr=1e-3,
        beta=Schedule(0.01),
        **kw,
    )
    wm = WorldModel(15, 28, hidden=(16,))
    return VAELearner(15, 28, cfg, world_model=wm, seed=0)


def random_batch(walk_run, n: int = 4, steps: int = 3) -> VAEBatch:
    import numpy as np

    from workers.models.body_state import pack

    frames = np.arange(n)[:, None] + np.arange(steps + 1)
    kin = walk_run.state(np.zeros(n * (steps + 1), int), frames.ravel())
    states = torch.as_tensor(pack(kin)).reshape(n, steps + 1, 15, 13)
    return VAEBatch(states, states.clone(), torch.zeros(n, steps, 28))


@pytest.mark.parametrize("objective", ["controlvae", "physicsvae", "pulse"])
@pytest.mark.parametrize("prior", ["standard_normal", "conditional", "learned"])
def test_every_objective_and_prior_updates(walk_run, objective, prior):
    torch.manual_seed(0)
    if objective == "physicsvae" and prior != "standard_normal":  # Eq. 1's KL is to N(0, I)
        with pytest.raises(ValueError, match="vae.prior: the physicsvae objective"):
            small_learner(objective, prior)
        return
    learner = small_learner(objective, prior)
    before = {k: v.clone() for k, v in learner.get_weights().state.items()}
    m = learner.update(random_batch(walk_run))
    assert math.isfinite(m["loss"]) and learner.version == 1
    after = learner.get_weights()
    assert after.version == 1
    assert any(not torch.equal(before[k], v) for k, v in after.state.items())


@pytest.mark.parametrize(("objective", "prior"), [("physicsvae", "standard_normal"), ("pulse", "learned")])
def test_plain_networks_update(walk_run, objective, prior):
    torch.manual_seed(0)
    learner = small_learner(objective, prior, network="plain", activation="relu")  # the moe policy stays moe
    before = {k: v.clone() for k, v in learner.get_weights().state.items()}
    m = learner.update(random_batch(walk_run))
    assert math.isfinite(m["loss"]) and any(
        not torch.equal(before[k], v) for k, v in learner.get_weights().state.items()
    )


def test_the_learners_kl_is_the_posterior_to_the_prior_by_hand(walk_run):
    """The KL term the learner optimises, worked from the encoder's own q and p: PhysicsVAE's to N(0, I),
    ½ Σ (μ² + σ² − 1 − 2 log σ), and PULSE's KL(q ‖ p) to its learned prior, which is not KL(p ‖ q). A
    learner with the KL reversed, averaged instead of summed over the latent, or taken to the wrong
    distribution fails this."""
    from workers.models import body_state

    batch = random_batch(walk_run)
    torch.manual_seed(0)
    learner = small_learner("physicsvae", "standard_normal", alpha=0.0)
    learner.before_update(batch)
    with torch.no_grad():
        _, terms = learner.loss(batch)
        s = body_state.features(torch.as_tensor(batch.states))
        q, _ = learner.vae.encode(s[:, :-1], s[:, 1:])
        by_hand = 0.5 * (q.mean**2 + torch.exp(2 * q.log_std) - 1 - 2 * q.log_std).sum(-1).mean()
    torch.testing.assert_close(terms["kl"], by_hand)
    assert float(by_hand) > 0

    torch.manual_seed(1)
    pulse = small_learner("pulse", "learned")
    pulse.before_update(batch)
    with torch.no_grad():
        _, terms = pulse.loss(batch)
        s = body_state.features(torch.as_tensor(batch.states[:, :-1]))
        goal = body_state.features(torch.as_tensor(batch.reference[:, 1:]))
        q, p = pulse.vae.encode(s, goal)
        forward = kl_divergence(Normal(q.mean, q.log_std.exp()), Normal(p.mean, p.log_std.exp())).sum(-1).mean()
        backward = kl_divergence(Normal(p.mean, p.log_std.exp()), Normal(q.mean, q.log_std.exp())).sum(-1).mean()
    torch.testing.assert_close(terms["kl"], forward)
    assert abs(float(forward - backward)) > 1e-3 * float(forward)


def test_non_finite_batch_is_skipped(walk_run):
    torch.manual_seed(0)
    learner = small_learner()
    learner.update(random_batch(walk_run))
    good = learner.get_weights()
    bad = random_batch(walk_run)
    bad.reference[0, 2, 3, 7] = float("nan")
    m = learner.update(bad)
    assert m["skipped_updates"] == 1 and learner.skipped_updates == 1 and learner.version == 1
    assert learner.get_weights() is good


def test_state_dict_round_trip_includes_optimizer(walk_run):
    torch.manual_seed(0)
    a = small_learner()
    a.update(random_batch(walk_run))
    b = small_learner()
    b.load_state_dict(a.state_dict())
    b.set_world_model_weights(Weights(0, a.world_model.state_dict()))  # frozen, not part of the VAE's state
    assert b.optimizer.state_dict()["state"], "optimizer state travels"
    a.generator.manual_seed(5)
    b.generator.manual_seed(5)
    ma, mb = a.update(random_batch(walk_run)), b.update(random_batch(walk_run))
    assert ma["loss"] == mb["loss"]
    for k, v in a.get_weights().state.items():
        torch.testing.assert_close(v, b.get_weights().state[k])


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("prior", "uniform", "vae.prior: unknown prior type 'uniform'"),
        ("objective", "gail", "vae.objective: unknown objective 'gail'"),
        ("beta", Schedule(-0.1), "vae.beta must be non-negative"),
    ],
)
def test_config_errors_name_the_key(field, value, message):
    with pytest.raises(ValueError, match=message):
        VAEConfig(**{field: value})


@pytest.mark.parametrize(
    ("objective", "field", "value", "message"),
    [
        ("physicsvae", "alpha", -1.0, "vae.alpha must be non-negative"),
        ("pulse", "lambda_regu", -0.1, "vae.lambda_regu must be non-negative"),
        ("controlvae", "gamma", 1.5, "vae.gamma must be in"),
    ],
)
def test_each_objective_checks_its_own_terms(objective, field, value, message):
    with pytest.raises(ValueError, match=message):
        vae_config(objective, **{field: value})
    with pytest.raises(ValueError, match="vae.objective: this section's objective is 'controlvae', got 'pulse'"):
        ControlVAEObjective(objective="pulse")


def test_each_objective_has_only_its_own_terms_and_its_learner_takes_only_its_section():
    """α is PhysicsVAE's, λ_regu PULSE's, Eq. 12/16's weights ControlVAE's; a learner of one objective refuses the
    shared part alone, which has none of them."""
    own = {"controlvae": {"gamma", "w_a1", "w_a2", "state_weights"}, "physicsvae": {"alpha", "physicsvae_reduction"},
           "pulse": {"lambda_regu"}}  # fmt: skip
    shared = {f.name for f in dataclasses.fields(VAEConfig)}
    for objective, terms in own.items():
        config = vae_config(objective)
        assert {f.name for f in dataclasses.fields(config)} - shared == terms and config.objective == objective
    with pytest.raises(TypeError, match="takes a PhysicsVAEObjective"):
        VAELearner(15, 28, VAEConfig(objective="physicsvae", prior="standard_normal"))


def test_controlvae_without_world_model_is_an_error():
    with pytest.raises(ValueError, match="needs a world model"):
        VAELearner(15, 28, ControlVAEObjective(), world_model=None)


def test_the_prior_switches_change_what_is_sampled(walk_run):
    """PULSE's Table 3 switches: the learned prior (off: N(0, I)) and the prior-residual task action (Eq. 4)."""
    s = torch.from_numpy(walk_run.features(np.zeros(64, int), np.arange(64)).astype(np.float32))
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(1)
    learned = small_learner("pulse", "learned").vae
    torch.manual_seed(1)
    plain = small_learner("pulse", "standard_normal").vae
    p = plain.prior_dist(s)
    assert torch.equal(p.mean, torch.zeros_like(p.mean)) and torch.equal(p.log_std, torch.zeros_like(p.log_std))
    z = p.rsample(g)
    assert abs(float(z.mean())) < 0.2 and float(z.std()) == pytest.approx(1.0, abs=0.2)
    q = learned.prior_dist(s)
    assert float((q.mean[0] - q.mean[32]).abs().max().detach()) > 1e-3  # the learned prior depends on the state
    assert float(q.log_std.max()) <= learned.prior.log_std_range[1] + 1e-6
    zero = torch.zeros_like(q.mean)
    with torch.no_grad():
        residual = learned.act(s, learned.task_latent(s, zero, prior_action=True))
        at_mean = learned.act(s, q.mean)
        absolute = learned.act(s, learned.task_latent(s, zero, prior_action=False))
    assert torch.allclose(residual, at_mean) and not torch.allclose(residual, absolute)
    assert torch.equal(plain.task_latent(s, zero, True), zero)  # N(0, I): the residual changes nothing


def test_single_state_starts_feed_the_normaliser_from_their_own_states(character):
    """A batch of single start states [N, 1] updates the state normaliser with `norm_states` instead."""
    from workers.models.world_model import WorldModel

    b, a = character.num_bodies, character.num_actions
    config = ControlVAEObjective(latent_dim=4, encoder_hidden=(16,), policy="mlp", policy_hidden=(16,), batch_size=3,
                       rollout_steps=2)  # fmt: skip
    learner = VAELearner(b, a, config, world_model=WorldModel(b, a, (16,), "elu", 1 / 30, "semi_implicit"))
    rng = np.random.default_rng(0)
    states = rng.normal(size=(3, 1, b, 13)).astype(np.float32)
    states[..., 3:7] = [1, 0, 0, 0]
    reference = np.repeat(states, 3, axis=1)
    norm = np.repeat(states[:, 0], 7, axis=0)  # 21 states
    learner.update(VAEBatch(states, reference, norm_states=norm))
    assert int(learner.vae.state_norm.count) == 21


def test_vae_nc_is_controlvae_with_a_unit_posterior():
    """ControlVAE §5.6's VAE-NC: prior N(0, I), posterior N(μ_q, I); only the prior type differs from ControlVAE."""
    from workers.learners.vae import VAEConfig, build_controller

    nc = VAEConfig(prior="standard_normal", latent_dim=3, encoder_hidden=(8,), policy="mlp", policy_hidden=(8,))
    assert nc.posterior_std == 1.0
    assert (
        vae_config(objective="pulse", prior="standard_normal").posterior_std is None
    )  # PULSE's no-prior row learns it
    torch.manual_seed(0)
    vae = build_controller(2, 4, nc)
    s, s_next = torch.randn(5, vae.state_norm.mean.shape[0]), torch.randn(5, vae.state_norm.mean.shape[0])
    q, p = vae.encode(s, s_next)
    assert torch.equal(q.log_std, torch.zeros(5, 3)) and torch.equal(p.log_std, torch.zeros(5, 3))
    assert torch.equal(p.mean, torch.zeros(5, 3))
    z = torch.stack([p.rsample(torch.Generator().manual_seed(i)) for i in range(400)])
    assert abs(float(z.mean())) < 0.05 and abs(float(z.std()) - 1.0) < 0.05  # sampling the prior is N(0, I)
    with pytest.raises(ValueError, match="posterior_std"):
        VAEConfig(posterior_std=0.0)


def test_pulses_mimic_goal_is_what_its_posterior_reads_and_shows_drift(walk_run):
    """With vae.goal=mimic the encoder reads PULSE's s_g-mimic of (state t, reference t + 1) through a
    normaliser of its own: the KL term equals the one worked from that goal, and moving the reference 1 m
    sideways (drift) changes it, where the reference-frame goal cannot see the move."""
    from workers.models import body_state
    from workers.models.tracking_goal import mimic_goal

    batch = random_batch(walk_run)
    moved = VAEBatch(batch.states, batch.reference.clone(), batch.actions)
    moved.reference[..., 1] += 1.0
    kls = {}
    for goal in ("mimic", "reference"):
        torch.manual_seed(0)
        learner = small_learner("pulse", "learned", goal=goal)
        learner.before_update(batch)
        with torch.no_grad():
            kls[goal] = [float(learner.loss(b)[1]["kl"]) for b in (batch, moved)]
    assert kls["reference"][0] == pytest.approx(kls["reference"][1], abs=1e-6)
    assert abs(kls["mimic"][0] - kls["mimic"][1]) > 1e-3

    torch.manual_seed(0)
    learner = small_learner("pulse", "learned", goal="mimic")
    learner.before_update(batch)
    assert learner.vae.goal_norm is not None and float(learner.vae.goal_norm.count) > 0
    with torch.no_grad():
        _, terms = learner.loss(moved)
        states = torch.as_tensor(moved.states)
        g = mimic_goal(states[:, :-1], torch.as_tensor(moved.reference[:, 1:]))
        q, p = learner.vae.encode(body_state.features(states[:, :-1]), g)
        by_hand = kl_divergence(Normal(q.mean, q.log_std.exp()), Normal(p.mean, p.log_std.exp())).sum(-1).mean()
    torch.testing.assert_close(terms["kl"], by_hand)
    with pytest.raises(ValueError, match="vae.goal"):
        vae_config(objective="controlvae", goal="mimic")


@pytest.mark.parametrize(
    ("objective", "prior"), [("controlvae", "conditional"), ("physicsvae", "standard_normal"), ("pulse", "learned")]
)
def test_draws_made_ahead_are_the_draws_the_loss_makes(walk_run, objective, prior):
    """What a compiled loss is given (`loss_inputs`): the same random numbers, as many, in the order the loss
    draws them, and this update's beta."""
    torch.manual_seed(0)
    learner, batch = small_learner(objective, prior), random_batch(walk_run)
    learner.before_update(batch)
    start = learner.generator.get_state()
    total, terms = learner.loss(batch)
    after_eager = learner.generator.get_state()
    learner.generator.set_state(start)
    inputs = learner.loss_inputs(batch)
    assert torch.equal(learner.generator.get_state(), after_eager)  # as many numbers drawn
    assert float(inputs["beta"]) == pytest.approx(learner.beta)
    total_ahead, terms_ahead = learner.loss(batch, **inputs)
    assert float(total_ahead) == float(total)
    assert {k: float(v) for k, v in terms_ahead.items()} == {k: float(v) for k, v in terms.items()}
