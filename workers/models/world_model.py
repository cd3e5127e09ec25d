"""The world model ω(s' | s, a) (ControlVAE §3.4.2, after SuperTrack; PhysicsVAE's simulation layer).

`WorldModel`: an MLP reads the features s of the current body state and the action, and
predicts each body's change of linear and angular velocity in the heading frame;
the new body state follows by integration (`body_state.integrate`). Inputs and
outputs are standardised with running statistics gathered from the training data.

`StateRegressor`: PhysicsVAE's simulation layer as Table 2 and the authors' code have it, a
plain MLP from (s, a) to the next state's features s′, trained by mean squared error. It
predicts features, not body states, so it cannot roll out a ControlVAE or task learner.

Both give `next_features(bs, a)`, the s′ that PhysicsVAE's α term compares.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from workers.models import body_state
from workers.models.nets import Normalizer, mlp


class WorldModel(nn.Module):
    def __init__(
        self,
        num_bodies: int,
        action_dim: int,
        hidden: Sequence[int] = (512, 512, 512, 512),
        act: str = "elu",
        dt: float = 1.0 / 30.0,
        integrator: str = "semi_implicit",
    ):
        super().__init__()
        if integrator not in body_state.INTEGRATORS:
            raise ValueError(f"unknown integrator {integrator!r}; expected one of {body_state.INTEGRATORS}")
        self.num_bodies = num_bodies
        self.action_dim = action_dim
        self.dt = dt
        self.integrator = integrator
        state_dim = 16 * num_bodies + 3
        self.state_norm = Normalizer(state_dim)
        self.action_norm = Normalizer(action_dim)
        self.delta_norm = Normalizer(6 * num_bodies)
        self.net = mlp(state_dim + action_dim, hidden, 6 * num_bodies, act, out_scale=0.1)

    @torch.no_grad()
    def observe(self, bs: torch.Tensor, action: torch.Tensor, bs_next: torch.Tensor) -> None:
        """Accumulate input and output statistics from true transitions [..., B, 13], [..., A], [..., B, 13]."""
        self.state_norm.update(body_state.features(bs))
        self.action_norm.update(action)
        self.delta_norm.update(body_state.heading_velocity_delta(bs, bs_next).flatten(-2))

    def delta(self, bs: torch.Tensor, action: torch.Tensor, s: torch.Tensor | None = None) -> torch.Tensor:
        """Predicted change of velocities [..., B, 6] in the heading frame of bs [..., B, 13]. `s`: bs's
        features, when the caller has them already (a rollout computes each state's features once)."""
        s = body_state.features(bs) if s is None else s
        x = torch.cat((self.state_norm(s), self.action_norm(action)), dim=-1)
        return self.delta_norm.denormalize(self.net(x)).unflatten(-1, (self.num_bodies, 6))

    def forward(self, bs: torch.Tensor, action: torch.Tensor, s: torch.Tensor | None = None) -> torch.Tensor:
        """The next body state [..., B, 13] (`s`: bs's features, if known; see `delta`)."""
        return body_state.integrate(bs, self.delta(bs, action, s), self.dt, self.integrator)

    def next_features(self, bs: torch.Tensor, action: torch.Tensor, s: torch.Tensor | None = None) -> torch.Tensor:
        """s′ [..., D]: the features of the next body state (`s`: bs's features, if known)."""
        return body_state.features(self(bs, action, s))

    def rollout(self, bs0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Open-loop prediction [N, T, B, 13] from start states [N, B, 13] under actions [N, T, A]."""
        out = []
        bs = bs0
        for t in range(actions.shape[1]):
            bs = self(bs, actions[:, t])
            out.append(bs)
        return torch.stack(out, dim=1)


class StateRegressor(nn.Module):
    """s′ = MLP(s, a): features of the body state and the action in, the next state's features out."""

    def __init__(self, num_bodies: int, action_dim: int, hidden: Sequence[int] = (1024, 1024), act: str = "relu"):
        super().__init__()
        self.num_bodies = num_bodies
        self.action_dim = action_dim
        state_dim = 16 * num_bodies + 3
        self.net = mlp(state_dim + action_dim, hidden, state_dim, act)

    @torch.no_grad()
    def observe(self, bs: torch.Tensor, action: torch.Tensor, bs_next: torch.Tensor) -> None:
        """Nothing to gather: the authors' layer reads its inputs as they are."""

    def next_features(self, bs: torch.Tensor, action: torch.Tensor, s: torch.Tensor | None = None) -> torch.Tensor:
        """s′ [..., D] from body states [..., B, 13] and actions [..., A] (`s`: bs's features, if known)."""
        s = body_state.features(bs) if s is None else s
        return self.net(torch.cat((s, action), dim=-1))
