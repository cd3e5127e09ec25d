"""Which runs a task stage accepts as its skill model, and the one-line refusals of the others."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from orchestrator.components.task import skill_model
from orchestrator.compose import register, validate
from orchestrator.upstream import StageError

CONF = Path(__file__).resolve().parents[2] / "conf"
register()


class StoredRun:
    """An upstream stage as the task reads it (orchestrator.stages.Upstream's interface), without a store."""

    def __init__(self, algo: str, state: dict, lineage: dict | None = None):
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            self.cfg = validate(compose("config", overrides=["run_dir=unused", f"algo={algo}", "scale=smoke"]))
        self.state, self.lineage, self.role = state, dict(lineage or {}), "skill"

    def describe(self) -> str:
        return f"stage skill ({self.cfg.algo.name}, run abc123)"

    def config(self):
        return self.cfg

    def checkpoint(self) -> dict:
        return self.state


def test_a_controlvae_run_gives_its_decoder_and_its_own_world_model():
    up = StoredRun("controlvae", {"vae": {"learner": {"module": {"w": 1}}}, "world_model": {"module": {"m": 2}}})
    skill = skill_model(up, world_model=True)
    assert skill["module"] == {"w": 1} and skill["prior_action"] and skill["world_model"][1] == {"m": 2}


def test_pulse_passes_its_prior_action_switch_and_has_no_world_model():
    up = StoredRun("pulse", {"vae": {"module": {"w": 1}}}, {"expert": "e" * 32})
    up.cfg.algo.pulse.prior_action = False
    assert skill_model(up, world_model=False)["prior_action"] is False
    with pytest.raises(StageError, match=r"stage skill \(pulse, run abc123\).*no world model.*trainer=ppo"):
        skill_model(up, world_model=True)


@pytest.mark.parametrize("algo", ["tracker", "amp", "simulation_layer", "task"])
def test_runs_without_a_vae_controller_are_refused_by_name(algo):
    with pytest.raises(StageError, match=rf"run abc123\): a {algo} run is not a skill model"):
        skill_model(StoredRun(algo, {}), world_model=False)


def test_a_checkpoint_without_vae_weights_is_refused():
    with pytest.raises(StageError, match="checkpoint has no vae state"):
        skill_model(StoredRun("controlvae", {"world_model": {}}), world_model=False)
