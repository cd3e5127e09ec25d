"""Every config group and preset composes and validates; bad values are refused with their key named."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from orchestrator.schema import ConfigError, register, validate

CONF = Path(__file__).resolve().parents[2] / "conf"
GROUPS = ["character", "motion", "algo", "model", "runtime", "tracking", "eval"]

register()


def composed(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["run_dir=unused", *overrides])


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize(("group", "option"), [(g, o) for g in GROUPS for o in options(g)])
def test_every_group_option_composes_and_validates(group, option):
    cfg = validate(composed(f"{group}={option}"))
    assert cfg.algo.name == "controlvae"


@pytest.mark.parametrize("experiment", options("experiment"))
def test_every_experiment_composes_and_validates(experiment):
    cfg = validate(composed(f"+experiment={experiment}"))
    assert cfg.preset == experiment


def test_defaults_are_the_laptop_run():
    cfg = validate(composed())
    assert cfg.runtime._target_.endswith("LocalRuntime") and cfg.motion.mirror
    assert "walker/turn_left0" in cfg.motion.clips and cfg.algo.vae.prior == "conditional"
    assert list(cfg.algo.world_model.hidden) == [256, 256, 256]  # model=small
    paper = validate(composed("model=paper"))
    assert list(paper.algo.vae.policy_hidden) == [512, 512, 512] and paper.algo.vae.num_experts == 6


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.vae.alpha=-1", "algo.vae.alpha must be non-negative"),
        ("algo.vae.beta.start=-0.5", "algo.vae.beta must be non-negative"),
        ("algo.vae.prior=gaussian", "algo.vae.prior: unknown prior type 'gaussian'"),
        ("runtime.rollout_workers=0", "runtime.rollout_workers must be at least 1"),
        ("motion.clips=[humanoid3d_walk,humanoid3d_moonwalk]", r"motion.clips\[1\]: humanoid3d_moonwalk"),
        ("algo.loop.iterations=0", "algo.loop.iterations must be at least 1"),
        ("character.control_hz=7", "character.sim_hz"),
    ],
)
def test_bad_values_are_refused_with_their_key(override, message):
    with pytest.raises(ConfigError, match=message):
        validate(composed(override))


def test_type_errors_are_refused_at_composition_with_the_key():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="algo.world_model.lr=fast"):
        composed("algo.world_model.lr=fast")
