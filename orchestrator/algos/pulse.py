"""PULSE (Luo et al. 2024): online distillation of a tracking expert into encoder, decoder and a learned prior.

DAgger-style (Alg. 1): the student (the VAE controller, z from the encoder E(z | s, s̃_{t+1})
given the reference's next state as the goal) acts in the rollout workers; its trajectories
go to the replay buffer; the learner (`orchestrator.components.pulse.PulseActor`) has the teacher, the
upstream `expert` stage, label the student's own states and takes Eq. 3's steps,
‖a_teacher − a‖² + λ·L_regu + β·KL(E ‖ R), with β annealed (`algo.vae.beta`). The student's
new weights are published for the next collection.

Table 3's rows are configurations: the learned prior (`algo.vae.prior=learned`, off:
`standard_normal`, N(0, I)), L_regu (`algo.vae.lambda_regu`, 0 turns it off) and the
prior-residual action of the downstream task (`algo.pulse.prior_action`, Eq. 4, read by a task
stage on this decoder). Evaluation: PULSE's success rate (the error averaged over the joints
within 0.5 m of the reference at all times; the stricter every-joint rate beside it) and MPJPE
tracking every clip with the encoder's mean, the action error against the teacher on the
student's own states, and random sampling from the prior (time until fall).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from orchestrator.algos.base import Component, ReplayFed, UpdateSchedule
from orchestrator.components.pulse import PulseActor
from orchestrator.components.replay import ReplayActor
from orchestrator.evaluation.protocols import evaluate_controller
from orchestrator.schema import ConfigError, MethodConfig, ReplayLoop
from orchestrator.upstream import expert_weights
from orchestrator.world import evaluation_sim_config
from workers.distill import teacher_actions
from workers.evaluation.controller import posterior_mean_action
from workers.evaluation.success import tracking_success
from workers.learners.vae import PulseObjective, build_controller
from workers.policies import VAEPolicy, expert_module


@dataclass
class PulseConfig:
    # PULSE's "prior-action" switch (Table 3): a downstream task policy acts as a residual on the learned
    # prior's mean, a = D(s, μ_task + μ_p) (Eq. 4). It changes nothing in the distillation itself; it is
    # part of the stage's config so that a task stage on this decoder reads it. Needs the learned prior.
    prior_action: bool = True


@dataclass
class PulseAlgo(MethodConfig):
    vae: PulseObjective = field(default_factory=PulseObjective)
    pulse: PulseConfig = field(default_factory=PulseConfig)
    loop: ReplayLoop = field(default_factory=ReplayLoop)


class Pulse(ReplayFed):
    config_class = PulseAlgo
    replay_buffers = 1
    needs = ("expert",)

    @classmethod
    def check_config(cls, algo: PulseAlgo) -> None:
        if algo.pulse.prior_action and algo.vae.prior != "learned":
            raise ConfigError(
                f"algo.pulse.prior_action: a residual on the prior's mean (PULSE Eq. 4) needs algo.vae.prior=learned, "
                f"got {algo.vae.prior!r} (set algo.pulse.prior_action=false)"
            )

    def __init__(self, cfg, character, upstream=None):
        super().__init__(cfg, character, upstream)
        self.teacher = None
        self.schedule = UpdateSchedule.of(cfg, "vae")

    def components(self) -> list[Component]:
        b, a = self.character.num_bodies, self.character.num_actions
        self.teacher = expert_weights(self.upstream["expert"])
        return [
            Component("replay", ReplayActor, (self.cfg, b, a), role="replay"),
            Component("vae", PulseActor, (self.cfg, b, a, self.upstream["expert"]), actor="learner-vae"),
        ]

    @classmethod
    def make_policy(cls, cfg, character) -> VAEPolicy:
        return VAEPolicy(character.num_bodies, character.num_actions, cfg.algo.vae, cfg.algo.loop.prior_probability)

    def publish(self, trainer) -> None:
        trainer.publish(trainer.runtime.get(trainer.runtime.call(trainer.handles["vae"], "get_weights")))

    def step(self, trainer) -> tuple[int, dict[str, float]]:
        cfg, rt, h = self.cfg, trainer.runtime, trainer.handles
        loop, vae = cfg.algo.loop, cfg.algo.vae
        t0 = time.perf_counter()
        infos, collected = self.exchange(trainer, "replay")
        metrics: dict[str, float] = {}
        if infos[-1]["size"] >= loop.warmup:
            n = self.schedule.due(collected)
            batches = rt.call(h["replay"], "sample_batches", n, vae.batch_size, vae.rollout_steps)
            m = rt.get(rt.call(h["vae"], "train", batches))
            trainer.check_alive("vae", m.pop("incarnation"))
            metrics.update({f"vae/{k}": float(v) for k, v in m.items()})
        self.publish(trainer)
        ends = sum(i["episode_ends"] for i in infos)
        metrics.update(
            {
                "loop/vae_updates": float(self.schedule.updates),
                "rollout/episode_ends": float(ends),
                "rollout/mean_episode_steps": collected / max(ends, 1),
                "throughput/step_s": time.perf_counter() - t0,
            }
        )
        return collected, metrics

    def evaluate(self, trainer, final: bool) -> dict[str, float]:
        character, library = self.character_and_library()
        weights = trainer.runtime.get(trainer.runtime.call(trainer.handles["vae"], "get_weights"))
        controller = build_controller(character.num_bodies, character.num_actions, self.cfg.algo.vae)
        controller.load_state_dict(weights.state)
        controller.eval().requires_grad_(False)
        visited: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

        def student(sim, bs):  # the encoder's mean given the reference's next state
            frames = sim.start_frame + sim.steps
            a = posterior_mean_action(controller, sim, bs)
            visited.append((bs.copy(), sim.clip_id.copy(), frames.copy(), a))
            return a

        with torch.no_grad():
            track = tracking_success(
                student, character, library, sim_config=evaluation_sim_config(self.cfg), seed=self.cfg.seed
            )
        states, clips, frames, actions = (np.concatenate(x) for x in zip(*visited, strict=True))
        teacher = self.teacher.state
        module = expert_module(teacher, character.num_bodies, character.num_actions)
        labels = teacher_actions(
            module, character, library, states, clips, frames, teacher["residual"], teacher["observation"]
        )
        metrics = {
            "eval/success_rate_pulse": float(track["success_rate_pulse"]),
            "eval/success_rate_every_joint": float(track["success_rate_every_joint"]),
            "eval/mpjpe_mm": float(track["mpjpe_mm"]),
            "eval/mpjpe_local_mm": float(track["mpjpe_local_mm"]),
            "eval/action_error": float(((actions - labels) ** 2).sum(-1).mean()),
        }
        iteration = trainer.state.iteration
        trainer.logger.log_dict(track, f"eval/{'final' if final else f'iter-{iteration:07d}'}-success.json")
        metrics.update(evaluate_controller(self.cfg, character, library, weights, trainer.logger, iteration, final))
        return metrics

    def progress(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"distill": f"{metrics.get('vae/distill', float('nan')):.3g}"}

    def state_dict(self) -> dict[str, Any]:
        return self.schedule.state_dict("vae")

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "credit" in state:  # a checkpoint written before the schedules had their learner's name
            state = {"vae_credit": state["credit"], "vae_updates": state["updates"]}
        self.schedule.load_state_dict(state, "vae")
