"""Device mixing caught on a CPU: torch's FakeTensorMode makes CUDA tensors that hold no values and need no GPU,
and refuses an operation between tensors of two devices as CUDA does (FakeTensorDeviceMismatchError).

Covered here: the tracking action (`posterior_mean`, what every tracking evaluation, recording and the Warp
transfer script drive the controller with) with the goal made on the GPU, as beside MuJoCo Warp on CUDA, and the
state read and the controller held on the CPU. A fake CUDA matrix product aborts the process on a CPU-only build of
torch, so nothing is computed on the fake GPU here: only moved to it and back. The controller is a stand-in that
concatenates as ours does: fake tensors hold no values, and our networks' normalizers branch on their counts
(`count == 0`), which fake tensors refuse (DataDependentOutputException), as they refuse every `.item()` of a
learner's metrics. So the learners' updates on a GPU are checked by the GPU smoke (`scripts/gpu-smoke.sh`), not here.
"""

from __future__ import annotations

import pytest
import torch
from torch import nn
from torch._subclasses.fake_tensor import FakeTensorDeviceMismatchError, FakeTensorMode

from workers.evaluation.controller import posterior_mean

CUDA = torch.device("cuda", 0)
S, G, Z, A = 6, 5, 2, 3


class Controller(nn.Module):
    """The shape of `VAEController.encode` / `.act` (posterior from [s, goal], action from [s, z]), no branches."""

    def __init__(self):
        super().__init__()
        self.q, self.pi = nn.Linear(S + G, 2 * Z), nn.Linear(S + Z, A)

    def encode(self, s, goal):
        mean, _ = self.q(torch.cat([s, goal], -1)).chunk(2, -1)
        return type("Posterior", (), {"mean": mean})(), None

    def act(self, s, z):
        return self.pi(torch.cat([s, z], -1))


def fake(module: nn.Module, device: torch.device | str) -> nn.Module:
    """`module` with fake parameters on `device`, called under FakeTensorMode (module.to would swap fake tensors in
    place, which they refuse)."""
    for m in module.modules():
        for name, p in list(m._parameters.items()):
            m._parameters[name] = nn.Parameter(torch.empty(p.shape, device=device))
    return module


def test_the_tracking_action_takes_a_goal_made_on_the_gpu_to_the_controller_on_the_cpu():
    controller_on = "cpu"
    with FakeTensorMode(allow_non_fake_inputs=True):
        controller = fake(Controller(), controller_on)
        s, goal = torch.zeros(4, S), torch.zeros(4, G, device=CUDA)
        with pytest.raises(FakeTensorDeviceMismatchError):  # what posterior_mean_action did before
            controller.encode(s, goal)
        action = posterior_mean(controller, s, goal)
    assert action.device.type == controller_on and tuple(action.shape) == (4, A)


def test_the_drivers_evaluation_runs_warp_on_the_cpu_where_it_sees_no_gpu_and_the_workers_keep_theirs(monkeypatch):
    """Evaluation, videos and the model's export build their simulator in the driver, which holds no Ray GPU (a
    cluster's may have none): on a GPU it does not see, the same engine on Warp's CPU device; the rollout workers,
    which see theirs through Ray, keep `sim.device`. This machine has no GPU; torch's count stands in for one."""
    from orchestrator.compose import compose, validate
    from orchestrator.world import collection_sim_config, evaluation_sim_config

    cfg = validate(compose(["scale=smoke", "sim.backend=warp", "sim.device=cuda", "run_dir=unused"]))
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    assert evaluation_sim_config(cfg).device == "cpu" and evaluation_sim_config(cfg).backend == "warp"
    assert collection_sim_config(cfg).device == "cuda"
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert evaluation_sim_config(cfg).device == "cuda"
