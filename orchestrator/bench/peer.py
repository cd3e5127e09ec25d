"""`bench peer`: our tracker pipeline against RLlib 2.60's PPO on the same humanoid, interleaved in one run.

Both sides train the same job, a PPO imitation policy on the walk clip with the
tracker's reward (`workers.rewards`), with the same policy and value MLP sizes,
the same batch (train batch and minibatch, one epoch), the same number of
environments stepped as `BatchedSim`s, one torch thread per process
(RLlib samples in its local env runner, `orchestrator.bench.peer_rllib`; ours runs
the local runtime with one rollout worker). Timed blocks alternate, ours then
RLlib's, and each pair gives a ratio; the table reports each side's median rate
and the median of the pairwise ratios, so that drift of a shared machine cancels.

- end to end: one training iteration (collect the batch, PPO update, weights
  published to the workers): our `Trainer.step()`, RLlib's `algo.train()`. RLlib's
  steps are its `num_env_steps_sampled_lifetime` difference, less the steps of the
  previous round's sampling-only call, which RLlib folds into its next `train()`
  result (counted as trained, they made its figure 1.5x too high before 2026-12-02).
- sampling only: the batch's environment steps with policy inference: our
  workers' `collect` calls (at once, on Ray), RLlib's `env_runner.sample`.

Our side runs as configured: `--ours local` (one process, one worker: the same
layout as RLlib's local env runner) or `--ours ray` with `--workers` rollout
actors and the PPO learner actor on the machine's cores, optionally with
`--overlap` (the next batch is collected while the learner trains). RLlib runs
its fastest layout measured here, sampling in the driver (0 env runners; one
remote runner measured slower, see `peer_rllib`).

Differences that remain: RLlib learns its action std (ours is fixed), normalises
actions into [-π, π], and its policy acts in absolute PD targets, ours as offsets
from the reference pose (the tracker's choice); neither changes the work per step.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from tempfile import TemporaryDirectory
from typing import Any


def _our_trainer(
    tmp: str,
    num_envs: int,
    hidden: tuple[int, ...],
    batch: int,
    minibatch: int,
    seed: int,
    runtime: str = "local",
    workers: int = 1,
    overlap: bool = False,
    sim_threads: int = 1,
):
    from orchestrator.build import untracked_trainer
    from orchestrator.compose import compose, validate

    sizes = "[" + ",".join(str(h) for h in hidden) + "]"
    overrides = [
        "algo=tracker",
        "scale=paper",
        "motion=walk",
        f"runtime={runtime}",
        f"runtime.rollout_workers={workers}",
        f"runtime.envs_per_worker={max(1, num_envs // workers)}",
        f"runtime.sim_threads={sim_threads}",
        f"algo.loop.collect_steps={max(1, batch // num_envs)}",
        f"algo.loop.overlap={str(overlap).lower()}",
        f"algo.ppo.policy_hidden={sizes}",
        f"algo.ppo.value_hidden={sizes}",
        f"algo.ppo.minibatch_size={minibatch}",
        "algo.ppo.epochs=1",
        "algo.loop.max_episode_steps=300",  # the gymnasium adapter's default episode cap
        "tracking=off",
        "progress=false",
        f"seed={seed}",
        f"run_dir={tmp}",
    ]
    cfg = validate(compose(overrides))
    rt, trainer = untracked_trainer(cfg)
    trainer.method.start(trainer)
    return cfg, rt, trainer


def run(
    num_envs: int,
    hidden: tuple[int, ...],
    batch: int,
    minibatch: int,
    rounds: int,
    warmup: int,
    seed: int,
    runtime: str = "local",
    workers: int = 1,
    overlap: bool = False,
    per_round: int = 2,
    sim_threads: int = 1,
) -> dict[str, Any]:
    import torch

    from orchestrator.bench import peer_rllib

    ray, _, _ = peer_rllib.import_rllib()  # a clear error when the extra is not installed
    torch.set_num_threads(1)
    started = not ray.is_initialized()
    if started:
        # Logical CPUs for our Ray actors (workers and learner); all run on this machine's cores.
        ray.init(num_cpus=max(os.cpu_count() or 1, workers + 2), include_dashboard=False, log_to_driver=False)
    env_config = {"max_episode_steps": 300}
    algo = None
    with TemporaryDirectory() as tmp:
        cfg, rt, trainer = _our_trainer(
            tmp, num_envs, hidden, batch, minibatch, seed, runtime, workers, overlap, sim_threads
        )
        try:
            algo = peer_rllib.build_config(num_envs, hidden, batch, minibatch, seed, 0, env_config).build_algo()
            steps = cfg.algo.loop.collect_steps
            last = None
            for _ in range(warmup):
                trainer.step()
                last = algo.train()
            rt.get(getattr(trainer.method, "pending", []))
            pairs: dict[str, list[tuple[float, float]]] = {"end_to_end": [], "sampling": []}
            # RLlib's lifetime count folds in the steps of the sampling-only calls below at its next
            # train(): they are taken off, or the end-to-end figure counts them as trained (1.5x here).
            sampled_apart = 0
            counted: list[tuple[float, float]] = []  # (ours, RLlib's) env steps of each end-to-end block
            for _ in range(rounds):
                # Our block ends when our actors are idle again (an overlapping collection is waited
                # for and timed here), so neither side's blocks run on the other's time.
                t0 = time.perf_counter()
                s0 = trainer.state.samples
                for _ in range(per_round):
                    trainer.step()
                rt.get(getattr(trainer.method, "pending", []))
                ours = (trainer.state.samples - s0) / (time.perf_counter() - t0)
                before = peer_rllib.lifetime_steps(last)
                t0 = time.perf_counter()
                for _ in range(per_round):
                    last = algo.train()
                theirs_steps = peer_rllib.lifetime_steps(last) - before - sampled_apart
                theirs = theirs_steps / (time.perf_counter() - t0)
                pairs["end_to_end"].append((ours, theirs))
                counted.append((trainer.state.samples - s0, theirs_steps))
                t0 = time.perf_counter()
                trajectories = rt.get([rt.call(w, "collect", steps) for w in trainer.workers])
                ours = sum(tr.num_transitions for tr in trajectories) / (time.perf_counter() - t0)
                sampled_apart, secs = peer_rllib.time_sampling(algo, 1, batch, 0)
                pairs["sampling"].append((ours, sampled_apart / secs))
        finally:
            if algo is not None:
                algo.stop()
            rt.shutdown()
            if started:
                ray.shutdown()
    out: dict[str, Any] = {
        "benchmark": "peer",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "rllib_version": ray.__version__,
        "num_envs": num_envs,
        "hidden": list(hidden),
        "train_batch_size": batch,
        "minibatch_size": minibatch,
        "rounds": rounds,
        "iterations_per_round": per_round,
        "torch_threads": 1,
        "ours": {"runtime": runtime, "rollout_workers": workers, "overlap": overlap, "sim_threads": sim_threads},
        "rllib": {"env_runners": 0},
    }
    for key, values in pairs.items():
        out[key] = {
            "ours_steps_per_s": statistics.median(o for o, _ in values),
            "rllib_steps_per_s": statistics.median(t for _, t in values),
            "ratio_median": statistics.median(o / t for o, t in values),
            "pairs": values,
        }
    out["end_to_end"]["steps_per_round"] = counted
    return out


def format_table(r: dict[str, Any]) -> str:
    lines = [
        f"peer benchmark: tracker on walk, {r['num_envs']} envs, MLPs {r['hidden']}, batch {r['train_batch_size']}"
        f"/{r['minibatch_size']}, 1 epoch, 1 torch thread, {r['rounds']} interleaved rounds, "
        f"RLlib {r['rllib_version']} (0 env runners); ours: runtime={r['ours']['runtime']}, "
        f"{r['ours']['rollout_workers']} worker(s), overlap={r['ours']['overlap']}, "
        f"sim_threads={r['ours'].get('sim_threads', 1)}",
        f"{'measurement':<14}{'ours steps/s':>14}{'RLlib steps/s':>15}{'ratio (median of pairs)':>26}",
    ]
    for key in ("sampling", "end_to_end"):
        x = r[key]
        lines.append(
            f"{key.replace('_', ' '):<14}{x['ours_steps_per_s']:>14,.0f}{x['rllib_steps_per_s']:>15,.0f}"
            f"{x['ratio_median']:>26.2f}"
        )
    return "\n".join(lines)
