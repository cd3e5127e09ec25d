"""The trained controller as an MLflow model: `mlflow.pytorch.log_model` with an input example and signature,
and beside it its weights alone, in a file that loads without unpickling.

The policy the rollout workers ran (`Method.make_policy` with the run's last weights) gives its
deterministic form (`Policy.deployable`: the VAE controller with z at its prior's mean, or the PPO
actor's mean), and an input example of one standing start from the first clip. Load it with
`mlflow.pytorch.load_model(<model uri>)`; the run's `model_uri` tag holds the uri. That model is a
pickle: loading it runs whatever code its file names, so load it only from a store that nobody else
can write to. The run's `weights/controller.pt` artifact holds the module's state_dict as plain
tensors: `torch.load(path, weights_only=True)` reads it without running code, and
`module.load_state_dict` puts it into the module that `deployable` builds from the run's config.
A tracking store that cannot take the model (the server is away) leaves it saved in `<run_dir>/model`
instead, with one warning; the run goes on (the weights are spooled with the run's other artifacts).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import torch

from orchestrator.tracking.base import RunLogger
from workers.body.character import Character
from workers.learners.base import Weights
from workers.motion.library import MotionLibrary
from workers.policies import Policy
from workers.sim.env import SimConfig, make_sim

log = logging.getLogger(__name__)

MODEL_NAME = "controller"
WEIGHTS_FILE = "controller.pt"  # in <run_dir>/weights/, logged as the artifact weights/controller.pt


def save_weights(module: torch.nn.Module, path: Path) -> None:
    """`module`'s state_dict as CPU tensors and nothing else, so that `torch.load(path, weights_only=True)` reads it."""
    state = {}
    for key, value in module.state_dict().items():
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"{type(module).__name__}.state_dict()[{key!r}] is a {type(value).__name__}, not a tensor")
        state[key] = value.detach().cpu().clone()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)


def deployable(
    policy: Policy, weights: Weights, character: Character, library: MotionLibrary, sim_config: SimConfig, seed: int
) -> tuple[torch.nn.Module, np.ndarray] | None:
    """(module, input example [1, obs_dim]) of `policy` with `weights`, from one standing start of the first
    clip in a simulator as `sim_config` says; None if the policy has no export."""
    policy.set_weights(weights)
    sim = make_sim(character, library, 1, sim_config, seed=seed)
    sim.reset(np.zeros(1, int), np.zeros(1, int), np.zeros(1, int))
    found = policy.deployable(sim, sim.body_states())
    if found is None:
        return None
    module, example = found
    return module.eval(), np.asarray(example, np.float32)


def log_policy(logger: RunLogger, module: torch.nn.Module, example: np.ndarray, run_dir: Path) -> str | None:
    """Log `module` as the run's MLflow model; its uri, or None when it was saved to `run_dir/model` instead."""
    import mlflow
    import mlflow.pytorch
    from mlflow.models import infer_signature

    uri = getattr(logger, "uri", None)
    if uri is None or logger.run_id is None:
        return None
    weights = run_dir / "weights" / WEIGHTS_FILE
    save_weights(module, weights)
    logger.log_artifact(weights, "weights")
    with torch.no_grad():
        output = module(torch.from_numpy(example)).numpy()
    signature = infer_signature(example, output)
    # Pinned rather than inferred: inference re-imports the whole environment (seconds) and drops +cpu anyway.
    requirements = [f"torch=={torch.__version__.split('+')[0]}", f"mlflow=={mlflow.__version__}"]
    # Pickled (not torch.export): the normalisers branch on their sample count, which export cannot trace.
    kwargs = dict(
        signature=signature, input_example=example, pip_requirements=requirements, serialization_format="pickle"
    )
    quiet = logging.getLogger("mlflow.pytorch")  # its warning about pickles, at every run
    level = quiet.level
    try:
        quiet.setLevel(logging.ERROR)
        mlflow.set_tracking_uri(uri)
        info = mlflow.pytorch.log_model(module, name=MODEL_NAME, run_id=logger.run_id, **kwargs)
    except Exception as e:  # noqa: BLE001 - any store failure: keep the model on disk, the run goes on
        where = run_dir / "model"
        shutil.rmtree(where, ignore_errors=True)
        mlflow.pytorch.save_model(module, str(where), **kwargs)
        log.warning("model not logged to %s (%s); saved in %s", uri, type(e).__name__, where)
        return None
    finally:
        quiet.setLevel(level)
    logger.set_tags({"model_uri": info.model_uri})
    return info.model_uri
