"""Every config group, method, experiment and scale composes and validates; bad values are refused with their key."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from orchestrator.algos.base import method_class
from orchestrator.compose import register, validate
from orchestrator.schema import ConfigError, sections_of

CONF = Path(__file__).resolve().parents[2] / "conf"
GROUPS = ["character", "motion", "algo", "runtime", "tracking", "scale"]

register()


def composed(*overrides: str, hydra: bool = False):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["run_dir=unused", *overrides], return_hydra_config=hydra)


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize(("group", "option"), [(g, o) for g in GROUPS for o in options(g)])
def test_every_group_option_composes_and_validates(group, option):
    cfg = validate(composed(f"{group}={option}"))
    assert cfg.algo.name == (option if group == "algo" else "controlvae")


@pytest.mark.parametrize(("algo", "scale"), [(a, s) for a in options("algo") for s in options("scale")])
def test_every_method_composes_with_every_scale(algo, scale):
    cfg = validate(composed(f"algo={algo}", f"scale={scale}"))
    method = method_class(cfg)
    assert type(cfg.algo) is method.config_class  # the method's own config, its sections and nothing else
    assert all(getattr(cfg.algo, section) is not None for section in sections_of(method.config_class))
    assert (CONF / "algo_scale" / f"{algo}_{scale}.yaml").exists()


@pytest.mark.parametrize(("experiment", "scale"), [(e, s) for e in options("experiment") for s in options("scale")])
def test_every_experiment_composes_with_every_scale(experiment, scale):
    cfg = validate(composed(f"+experiment={experiment}", f"scale={scale}"))
    assert cfg.preset == experiment
    assert cfg.sweep_seeds == ("0" if scale == "smoke" else "0,1,2")


def test_scales_set_the_budget_of_each_method():
    smoke, laptop, paper = (validate(composed("algo=amp", f"scale={s}")) for s in ("smoke", "laptop", "paper"))
    assert smoke.algo.loop.iterations < laptop.algo.loop.iterations < paper.algo.loop.iterations
    assert list(paper.algo.ppo.policy_hidden) == [1024, 512] and paper.algo.ppo.clip == 0.02  # AMP Table 4
    assert paper.algo.discriminator.w_gp == 10.0 and paper.algo.discriminator.loss == "lsgan"


def test_defaults_are_the_laptop_run():
    cfg = validate(composed())
    # On a Ray started for the run (every core, the dashboard); runtime=local is the single-process mode.
    assert cfg.runtime._target_.endswith("RayRuntime") and cfg.runtime.address is None and cfg.motion.mirror
    assert "walker/turn_left0" in cfg.motion.clips and cfg.algo.vae.prior == "conditional"
    assert list(cfg.algo.world_model.hidden) == [256, 256, 256]  # algo_scale/controlvae_laptop
    assert not hasattr(cfg.algo, "ppo") and not hasattr(cfg.algo, "discriminator")
    assert cfg.runtime.learner_compile == "eager" and cfg.runtime.pin_cores == "auto"
    paper = validate(composed("scale=paper"))
    assert list(paper.algo.vae.policy_hidden) == [512, 512, 512] and paper.algo.vae.num_experts == 6
    # ControlVAE's schedule: 2,048 states per epoch, 8 updates of 512 x 8 and of 512 x 24 -> ratios 16 and 48.
    loop, r = paper.algo.loop, paper.runtime
    assert r.rollout_workers * r.envs_per_worker * loop.collect_steps == 2048
    assert dict(loop.replay_ratios) == {"world_model": 16, "vae": 48}
    assert 8 * 512 * 8 / 2048 == 16 and 8 * 512 * 24 / 2048 == 48
    assert not loop.end_on_fall and loop.max_episode_steps == 512 and loop.balance_every == 200
    assert paper.algo.loop.vae_starts == "states" and paper.algo.loop.switch_rate > 0
    # The laptop's, by measurement (conf/algo_scale/controlvae_laptop.yaml).
    assert cfg.algo.loop.end_on_fall and cfg.algo.loop.vae_starts == "windows" and cfg.algo.loop.balance_every == 0


def test_ablation_gp_names_its_loss_and_penalty_placement():
    cfg = composed("+experiment=ablation_gp", hydra=True)
    assert cfg.algo.name == "amp" and cfg.motion.clips == ["humanoid3d_walk"]
    assert cfg.algo.discriminator.loss == "lsgan" and cfg.algo.discriminator.gp_on == "data"
    assert cfg.algo.discriminator.gp_features == "raw"  # Eq. 8 on Φ as written; algo=amp keeps the normalised
    assert validate(composed("algo=amp")).algo.discriminator.gp_features == "normalised"
    paper = validate(composed("algo=amp", "scale=paper")).algo.discriminator  # Table 4: SGD, momentum 0.9, 1e-5
    assert (paper.optimizer, paper.momentum, paper.lr) == ("sgd", 0.9, 1e-5)
    assert validate(composed("algo=amp", "scale=laptop")).algo.discriminator.optimizer == "adam"
    params = cfg.hydra.sweeper.params
    assert params["algo.discriminator.w_gp"] == "0,1,10,40" and params["seed"] == "0,1,2"
    assert cfg.hydra.callbacks.sweep.compare_by == "algo.discriminator.w_gp"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.vae.w_a2=-1", "algo.vae.w_a2 must be non-negative"),
        ("algo.vae.beta.start=-0.5", "algo.vae.beta must be non-negative"),
        ("algo.vae.prior=gaussian", "algo.vae.prior: unknown prior type 'gaussian'"),
        ("runtime.rollout_workers=0", "runtime.rollout_workers must be at least 1"),
        ("runtime.learner_compile=off", "runtime.learner_compile must be one of"),
        ("runtime.pin_cores=always", "runtime.pin_cores must be one of"),
        ("runtime.worker_gpus=-1", "runtime.worker_gpus must be non-negative"),
        ("sim.backend=mjx", "sim.backend must be one of"),
        ("sim.device=gpu0", "sim.device must be cpu, cuda or cuda:N"),
        ("motion.clips=[humanoid3d_walk,humanoid3d_moonwalk]", r"motion.clips\[1\]: humanoid3d_moonwalk"),
        ("algo.loop.iterations=0", "algo.loop.iterations must be at least 1"),
        ("character.control_hz=7", "character.sim_hz"),
        ("algo._target_=orchestrator.trainer.Trainer", "algo._target_: cannot use 'orchestrator.trainer.Trainer'"),
        # Numbers no generator or optimiser takes (torch's Adam refuses lr=nan only when it is built, mid-run).
        ("algo.world_model.lr=nan", r"algo.world_model.lr: nan is not a finite number"),
        ("algo.vae.beta.start=inf", r"algo.vae.beta.start: inf is not a finite number"),
        ("seed=-1", r"seed: -1 is outside 0 \.\.\. 4294967295"),
        ("seed=4294967296", r"seed: 4294967296 is outside 0 \.\.\. 4294967295"),
    ],
)
def test_bad_values_are_refused_with_their_key(override, message):
    with pytest.raises(ConfigError, match=message):
        validate(composed(override))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        # Negative reward weights.
        (("algo=amp", "algo.amp.style_weight=-1"), "algo.amp.style_weight must be non-negative"),
        (("algo=amp", "algo.amp.task_weight=-0.5"), "algo.amp.task_weight must be non-negative"),
        (("algo=tracker", "algo.imitation.weights.pose=-2"), "algo.imitation.weights.pose must be non-negative"),
        (("algo=tracker", "+algo.imitation.weights.style=1"), "algo.imitation.weights.style: unknown term"),
        (("algo=amp", "algo.discriminator.w_gp=-1"), "algo.discriminator: w_gp and logit_reg must be non-negative"),
        (("algo=amp", "algo.discriminator.gp_on=policy"), "algo.discriminator: unknown gradient penalty placement"),
        (("algo=amp", "algo.ppo.optimizer=rmsprop"), "algo.ppo: PPOConfig.optimizer must be"),
        (("algo=physicsvae", "algo.vae.physicsvae_reduction=max"), "algo.vae.physicsvae_reduction: unknown"),
        (("algo=physicsvae", "algo.vae.alpha=-1"), "algo.vae.alpha must be non-negative"),
        (("algo=amp", "algo.discriminator.gp_features=whitened"), "algo.discriminator: gp_features: unknown"),
        (("algo=amp", "algo.discriminator.optimizer=lbfgs"), "algo.discriminator: optimizer: unknown"),
    ],
)
def test_method_sections_are_checked_with_their_key(overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate(composed(*overrides))


@pytest.mark.parametrize(
    "overrides",
    [
        ("algo=amp", "algo.world_model.lr=0.1"),  # a section of another method
        ("algo=tracker", "algo.discriminator.w_gp=1"),
        ("algo=amp", "algo.loop.balance_every=4"),  # ControlVAE's data balancing
        ("algo=physicsvae", "algo.loop.overlap=true"),  # PPO's
        ("algo=tracker", "algo.loop.warmup=10"),  # a replay-fed method's
        ("algo=controlvae", "algo.vae.alpha=0.1"),  # PhysicsVAE's term of the VAE section
        ("algo=physicsvae", "algo.vae.lambda_regu=0.1"),  # PULSE's
    ],
)
def test_a_key_the_methods_config_lacks_is_refused_at_composition_with_the_key(overrides):
    from hydra.errors import ConfigCompositionException

    key = overrides[1].split("=")[0]
    with pytest.raises(ConfigCompositionException, match=key.replace(".", r"\.")):
        composed(*overrides)


def plain(*overrides: str) -> dict:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(composed(*overrides), resolve=True)


def test_a_key_the_methods_config_lacks_is_refused_by_validate_with_the_key():
    with pytest.raises(ConfigError, match=r"^algo.ppo.clip: the controlvae method .* has no ppo section"):
        validate(composed("algo=controlvae", "+algo.ppo.clip=0.1"))  # appended on the command line
    amp = plain("algo=amp")
    amp["algo"]["world_model"] = {"lr": 0.1}
    with pytest.raises(ConfigError, match=r"^algo.world_model.lr: the amp method \(orchestrator.algos.amp.AMP\) has"):
        validate(amp)
    amp = plain("algo=amp")
    amp["algo"]["loop"]["vae_starts"] = "windows"
    with pytest.raises(ConfigError, match=r"^algo.loop.vae_starts: the amp method .* has no such loop setting"):
        validate(amp)


def test_a_config_an_earlier_version_stored_reads_back_without_its_other_methods_keys():
    """Before each method had its own config, a stored config had every section (null where unused) and every
    method's loop knobs; read back from a store, those are dropped and the rest is the method's config."""
    now = plain("algo=tracker")
    former = plain("algo=tracker")
    former["algo"].update(vae=None, world_model=None, discriminator=None)
    former["algo"]["loop"].update(vae_starts="states", balance_every=200, warmup=1000)
    assert validate(former, shipped_only=True) == validate(now)
    with pytest.raises(ConfigError, match="^algo.vae: the tracker method"):  # a user's own config is not forgiven
        validate(former)


def test_type_errors_are_refused_at_composition_with_the_key():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="algo.world_model.lr=fast"):
        composed("algo.world_model.lr=fast")


def test_pulse_prior_action_needs_the_learned_prior():
    with pytest.raises(ConfigError, match="algo.pulse.prior_action: a residual on the prior's mean"):
        validate(composed("algo=pulse", "algo.vae.prior=standard_normal"))
    cfg = validate(composed("algo=pulse", "algo.vae.prior=standard_normal", "algo.pulse.prior_action=false"))
    assert cfg.algo.vae.prior == "standard_normal" and cfg.algo.needs == {
        "expert": "tracker algo.imitation.observation=mimic"
    }


def test_stage_needs_are_checked_with_the_key_named():
    with pytest.raises(ConfigError, match="algo.needs.world_model: the physicsvae method needs a world_model stage"):
        validate(composed("algo=physicsvae", "algo.needs.world_model="))
    with pytest.raises(ConfigError, match="algo.needs.teacher: the demos method does not use a teacher stage"):
        validate(composed("algo=demos", "+algo.needs.teacher=tracker"))
    with pytest.raises(ConfigError, match="algo.vae.prior: the physicsvae objective"):
        validate(composed("algo=physicsvae", "algo.vae.prior=learned"))


def test_stage_overrides_reach_the_stages_above_and_bad_ones_name_the_need():
    from orchestrator import stages

    cfg = validate(composed("algo=physicsvae", '+stage_overrides.tracker=["algo.loop.iterations=9"]'))
    demos = stages.upstream_config(cfg, "demos", "demos")
    expert = stages.upstream_config(demos, "tracker", "expert")
    assert expert.algo.loop.iterations == 9 and expert.algo.name == "tracker"
    assert stages.config_hash(cfg) == stages.config_hash(validate(composed("algo=physicsvae")))  # hashed above
    # What a run is expected to take is not what it computes; what it computes is.
    same = validate(composed("algo=physicsvae", "algo.loop.expected_minutes=12"))
    assert stages.config_hash(same) == stages.config_hash(cfg)
    assert stages.config_hash(validate(composed("algo=physicsvae", "algo.loop.iterations=61"))) != stages.config_hash(
        cfg
    )
    with pytest.raises(ConfigError, match=r"algo.needs.expert \(tracker algo.loop.iterationz=3\): Key 'iterationz'"):
        stages.upstream_config(demos, "tracker algo.loop.iterationz=3", "expert")


def test_the_task_presets_name_their_skill_stages():
    """ablation_prior: a skill stage per prior and seed; ablation_prior_pulse: PULSE Table 3's first and last
    rows as pulse stages; ablation_sigma: one flat-ground physicsvae stage (PhysicsVAE §5.5.2) for every sigma
    and terrain."""
    prior = validate(composed("+experiment=ablation_prior", "algo.task.skill_prior=standard_normal", "seed=2"))
    assert prior.algo.needs == {"skill": "controlvae algo.vae.prior=standard_normal seed=2"}
    first = validate(composed("+experiment=ablation_prior_pulse", "pulse_row=first", "seed=1"))
    assert first.algo.task.skill_prior == "standard_normal" and first.algo.task.task == "vr"
    assert first.algo.needs["skill"] == (
        "pulse algo.vae.prior=standard_normal algo.pulse.prior_action=false algo.vae.lambda_regu=0 seed=1"
    )
    full = validate(composed("+experiment=ablation_prior_pulse"))
    assert full.algo.task.skill_prior == "learned" and full.algo.needs["skill"].startswith(
        "pulse algo.vae.prior=learned"
    )
    sigma = validate(composed("+experiment=ablation_sigma", "terrain.kind=rough", "algo.task.sigma=0.5"))
    assert sigma.algo.needs == {"skill": "physicsvae"} and sigma.terrain.kind == "rough"
    assert sigma.algo.task.trainer == "ppo" and sigma.algo.task.task == "point_goal"
    assert sigma.algo.task.reward == "progress"  # PhysicsVAE Sec. 5.2's point-goal reward
    with pytest.raises(ConfigError, match="algo.task.trainer"):
        validate(composed("algo=task", "algo.task.trainer=mpc"))
    with pytest.raises(ConfigError, match="terrain.kind"):
        validate(composed("algo=task", "terrain.kind=sand"))


def test_the_task_methods_ppo_trainer_is_its_variant_for_every_class_level_question(character):
    """`algo=task algo.task.trainer=ppo` runs PPO's loop: the class the trainer builds, the policy its workers run
    and the learner it reads are the PPO variant's, asked of the class (as preflight and the rollout actor do)
    without building the method."""
    from orchestrator.algos.task import Task, TaskPPO
    from workers.task.policy import TaskPPOPolicy, TaskRolloutPolicy

    model_cfg = validate(composed("algo=task", "scale=smoke"))
    ppo_cfg = validate(composed("algo=task", "scale=smoke", "algo.task.trainer=ppo"))
    model, ppo = method_class(model_cfg), method_class(ppo_cfg)
    assert (model, ppo) == (Task, TaskPPO)
    assert (model.learner_key, ppo.learner_key) == ("task", "ppo")
    assert type(model.make_policy(model_cfg, character)) is TaskRolloutPolicy
    assert type(ppo.make_policy(ppo_cfg, character)) is TaskPPOPolicy
