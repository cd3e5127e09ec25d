"""PhysicsVAE's learner actors, trained on a fixed dataset of expert demonstrations: the simulation layer and the VAE.

Each is built with the upstream stages it reads (`orchestrator.upstream.Upstream`, small), and
downloads the demos (and the frozen layer) from the tracking store itself, so that a
restarted actor, or one on another node, needs nothing from the driver. It splits the
episodes into training and held-out rollouts (`algo.offline.holdout_rollouts`), computes
the features s of every stored state once (the dataset fixes them; each batch takes its
windows' rows), and trains one epoch per `train_epoch` call: as many updates as it takes for
the batches to cover the training transitions once, at the epoch's learning rate
(×`lr_decay` every `decay_every` epochs, PhysicsVAE's schedule), in `algo.offline.precision`.
`validate` measures the held-out rollouts (in float32).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from orchestrator.components.base import LearnerActor, compiled, learner_device
from orchestrator.schema import Config
from orchestrator.upstream import Upstream, layer_state, load_demos
from orchestrator.world import seed_of
from workers.demos import DemoSet
from workers.learners.vae import VAEBatch, VAELearner
from workers.learners.world_model import WorldModelBatch, WorldModelConfig, WorldModelLearner, build_world_model
from workers.losses.kl import latent_usage
from workers.models import body_state
from workers.models.world_model import WorldModel


class OfflineActor(LearnerActor):
    window: int  # transitions per sampled window

    def __init__(self, cfg: Config, demos: DemoSet | Upstream, key: int):
        super().__init__(cfg, seed_offset=key)
        self.cfg = cfg
        self.demos = demos if isinstance(demos, DemoSet) else load_demos(demos)[0]
        holdout = cfg.algo.offline.holdout_rollouts
        self.train_starts = self.demos.window_starts(self.window, self.demos.episodes_of(False, holdout))
        self.heldout_starts = self.demos.window_starts(self.window, self.demos.episodes_of(True, holdout))
        if len(self.train_starts) == 0:
            raise ValueError(f"the demos hold no training window of {self.window} transitions")
        self.rng = np.random.default_rng(seed_of(cfg, key + 1))
        self.epoch = 0
        with torch.no_grad():
            self.features = body_state.features(torch.from_numpy(self.demos.states))  # [S, D], once

    def window_features(self, starts: np.ndarray) -> torch.Tensor:
        """s [N, window+1, D] of the windows at `starts`, from the features computed once."""
        return self.features[torch.from_numpy(starts[:, None] + np.arange(self.window + 1))]

    @property
    def batch_size(self) -> int:
        raise NotImplementedError

    def batch(self, starts: np.ndarray) -> Any:
        raise NotImplementedError

    def train_epoch(self) -> dict[str, Any]:
        off = self.cfg.algo.offline
        lr = self.base_lr * off.lr_decay ** (self.epoch // off.decay_every)
        for group in self.learner.optimizer.param_groups:
            group["lr"] = lr
        updates = max(1, math.ceil(len(self.train_starts) / self.batch_size))  # one pass over the windows
        metrics = []
        bfloat16 = off.precision == "bfloat16"
        for _ in range(updates):
            starts = self.rng.choice(self.train_starts, size=self.batch_size)
            batch = self.batch(starts)
            with torch.autocast(self.learner.device.type, dtype=torch.bfloat16, enabled=bfloat16):
                metrics.append(self.learner.update(batch))
        self.epoch += 1
        out = self.report(metrics)
        out["epoch"] = float(self.epoch)
        return out

    def heldout(self, limit: int = 4096) -> np.ndarray:
        starts = self.heldout_starts if len(self.heldout_starts) else self.train_starts
        if len(starts) > limit:
            starts = np.random.default_rng(0).choice(starts, size=limit, replace=False)
        return np.sort(starts)

    def state_dict(self) -> dict[str, Any]:
        return {"learner": self.learner.state_dict(), "epoch": self.epoch, "rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state["learner"])
        self.epoch = int(state["epoch"])
        self.rng.bit_generator.state = state["rng"]


class SimulationLayerActor(OfflineActor):
    """PhysicsVAE's simulation layer: the world model on T_w-step windows of the expert's (state, action)."""

    def __init__(self, cfg: Config, demos: DemoSet | Upstream, num_bodies: int, action_dim: int):
        self.window = cfg.algo.world_model.rollout_steps
        super().__init__(cfg, demos, 2)
        wm = cfg.algo.world_model
        self.learner = compiled(
            WorldModelLearner(num_bodies, action_dim, 1.0 / cfg.character.control_hz, wm, learner_device(cfg)), cfg
        )
        self.base_lr = wm.lr

    @property
    def batch_size(self) -> int:
        return self.cfg.algo.world_model.batch_size

    def batch(self, starts: np.ndarray) -> WorldModelBatch:
        states, actions = self.demos.windows(starts, self.window)
        return WorldModelBatch(torch.from_numpy(states), torch.from_numpy(actions), self.window_features(starts))

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Open-loop error on held-out windows: body positions (m, relative to nothing: world frame) and
        the loss terms, after one step and after T_w steps."""
        states, actions = self.demos.windows(self.heldout(), self.window)
        if self.cfg.algo.world_model.kind == "regress":  # features only: no body positions to compare
            model = self.learner.model.eval()
            s, a = self.learner.tensor(states), self.learner.tensor(actions)
            mse = ((model.next_features(s[:, :-1], a) - body_state.features(s[:, 1:])) ** 2).mean()
            return {"heldout_feature_mse_1": float(mse)}
        predicted = self.learner.predict(states[:, 0], actions)
        err = (predicted[..., :3] - self.learner.tensor(states[:, 1:, :, :3])).norm(dim=-1).mean(-1)  # [N, T]
        return {"heldout_pos_error_1": float(err[:, 0].mean()), "heldout_pos_error_T": float(err[:, -1].mean())}


class PhysicsVAEActor(OfflineActor):
    """PhysicsVAE's VAE (Eq. 1) on the expert's transitions, through the frozen simulation layer."""

    def __init__(
        self,
        cfg: Config,
        demos: DemoSet | Upstream,
        num_bodies: int,
        action_dim: int,
        layer: tuple[WorldModelConfig, dict[str, Any]] | Upstream,
    ):
        """`layer`: the world_model stage whose frozen layer this VAE learns through (its network's size is that
        stage's `algo.world_model`, read from it), or that config and state dict."""
        self.window = cfg.algo.vae.rollout_steps
        super().__init__(cfg, demos, 3)
        layer_config, layer_weights = layer if isinstance(layer, tuple) else (layer.config().algo.world_model, layer)
        self.world_model = build_world_model(num_bodies, action_dim, layer_config, 1.0 / cfg.character.control_hz)
        self.world_model.load_state_dict(layer_weights if isinstance(layer_weights, dict) else layer_state(layer))
        self.learner = compiled(
            VAELearner(num_bodies, action_dim, cfg.algo.vae, self.world_model, seed_of(cfg, 4), learner_device(cfg)),
            cfg,
        )
        self.base_lr = cfg.algo.vae.lr

    @property
    def batch_size(self) -> int:
        return self.cfg.algo.vae.batch_size

    def batch(self, starts: np.ndarray) -> VAEBatch:
        states, actions = self.demos.windows(starts, self.window)
        return VAEBatch(
            torch.from_numpy(states), actions=torch.from_numpy(actions), features=self.window_features(starts)
        )

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """On held-out expert transitions, with z = μ_q(s_t, s_{t+1}): the action error ‖a − a'‖², and the
        simulation layer's next state from the decoder's action against the expert's, ‖s_{t+1} − W(s_t, a')‖²
        in features (what Eq. 1's α term weighs) and in body positions (m). Measured for every α, 0 included.
        And how the posterior uses its latent there (`workers.losses.kl.latent_usage`): the KL, its share per
        dimension and the active dimensions, where a collapse under a large β shows."""
        vae = self.learner.vae.eval()
        states, actions = self.demos.windows(self.heldout(), 1)
        tensor = self.learner.tensor
        s = body_state.features(tensor(states))
        q, _ = vae.encode(s[:, 0], s[:, 1])
        a = vae.act(s[:, 0], q.mean)
        start = tensor(states[:, 0])
        usage = latent_usage(q.mean, q.log_std)
        out = {
            "heldout_action_error": float(((a - tensor(actions[:, 0])) ** 2).sum(-1).mean()),
            "heldout_sim_error": float(((self.world_model.next_features(start, a) - s[:, 1]) ** 2).sum(-1).mean()),
            "heldout_kl": float(usage["kl"]),
            "latent_active_dims": float(usage["active_dims"]),
            **{f"latent_kl/{d:02d}": float(v) for d, v in enumerate(usage["kl_per_dim"])},
        }
        if isinstance(self.world_model, WorldModel):  # a regress layer predicts features, not body positions
            nxt = self.world_model(start, a)
            pos = (nxt[..., :3] - tensor(states[:, 1, :, :3])).norm(dim=-1).mean(-1)
            out["heldout_next_pos_error"] = float(pos.mean())
        return out

    def get_weights(self):
        return self.learner.get_weights()
