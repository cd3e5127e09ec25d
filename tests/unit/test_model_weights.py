"""The weights-only form of the logged model: beside the pickled MLflow model, `weights/controller.pt` holds the
module's state as plain tensors, which `torch.load(weights_only=True)` reads without unpickling any code."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from orchestrator.tracking.mlflow import MlflowLogger
from orchestrator.tracking.model import WEIGHTS_FILE, log_policy, save_weights


def controller() -> torch.nn.Module:
    """Parameters and buffers (BatchNorm's running statistics and its int64 batch count), in eval mode."""
    torch.manual_seed(3)
    module = torch.nn.Sequential(torch.nn.Linear(5, 8), torch.nn.BatchNorm1d(8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
    module.train()
    module(torch.randn(16, 5))  # moves the running statistics off their initial 0 and 1
    return module.eval()


def test_the_weights_file_loads_with_weights_only_and_equals_the_modules_state(tmp_path):
    module = controller()
    path = tmp_path / "w.pt"
    save_weights(module, path)
    state = torch.load(path, weights_only=True)
    expected = module.state_dict()
    assert list(state) == list(expected)
    for key, value in expected.items():
        assert state[key].dtype == value.dtype and torch.equal(state[key], value), key
    assert state["1.num_batches_tracked"].item() == 1
    rebuilt = torch.nn.Sequential(
        torch.nn.Linear(5, 8), torch.nn.BatchNorm1d(8), torch.nn.Tanh(), torch.nn.Linear(8, 2)
    ).eval()
    rebuilt.load_state_dict(state)
    x = torch.randn(4, 5)
    assert torch.equal(rebuilt(x), module(x))


def test_log_policy_logs_the_weights_beside_the_pickled_model(tmp_path):
    """A real MLflow store (SQLite in the run directory): the run's artifact weights/controller.pt loads with
    weights_only=True; the MLflow model's own file is a pickle of the module, which weights_only refuses."""
    import mlflow
    from mlflow.tracking import MlflowClient

    module = controller()
    logger = MlflowLogger(None, "weights", run_dir=tmp_path / "run", background=False)
    try:
        model_uri = log_policy(logger, module, np.zeros((1, 5), np.float32), tmp_path / "run")
        logger.flush()
    finally:
        logger.close()
    assert model_uri is not None
    client = MlflowClient(logger.uri)
    assert [f.path for f in client.list_artifacts(logger.run_id, "weights")] == [f"weights/{WEIGHTS_FILE}"]
    local = client.download_artifacts(logger.run_id, f"weights/{WEIGHTS_FILE}", str(tmp_path / "down"))
    state = torch.load(local, weights_only=True)
    assert set(state) == set(module.state_dict())
    assert all(torch.equal(state[k], v) for k, v in module.state_dict().items())

    location = client.get_logged_model(model_uri.removeprefix("models:/")).artifact_location
    pickled = mlflow.artifacts.download_artifacts(f"{location}/data/model.pth", dst_path=str(tmp_path / "model"))
    with pytest.raises(Exception, match="Weights only load failed"):
        torch.load(pickled, weights_only=True)
