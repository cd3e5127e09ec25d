"""The RLlib side of the peer comparison (`bench peer`): RLlib 2.60's PPO on our humanoid.

What is compared: the same PPO training job (imitation of a reference clip by the
humanoid, DeepMimic-style reward) run by our pipeline and by RLlib's PPO, on the same
simulator, network sizes, batch sizes and cores. Both figures are environment steps
per second:

- end to end: `algo.train()` iterations (sample a train batch, one PPO epoch of
  minibatch SGD, weight sync, RLlib's metrics), after `warmup` untimed iterations;
  steps counted from RLlib's own `num_env_steps_sampled_lifetime`;
- sampling only: the env runner's `sample(num_timesteps=train_batch_size)`, policy
  inference with exploration included, `iterations` times (the same number of steps).

How RLlib is set up (new API stack, torch, CPU):

- environment: `workers.sim.gym_env`'s "MocapHumanoidImitation-v0", vectorised by OUR
  batched simulator (`gym_env_vectorize_mode=VECTOR_ENTRY_POINT`: one
  `HumanoidImitationVectorEnv` over one `BatchedSim` of `num_envs` environments per env
  runner, NEXT_STEP autoreset, the only mode RLlib's SingleAgentEnvRunner reads
  correctly). RLlib normalises actions (its default): the policy's outputs are
  unsquashed from [-1, 1] into the action box [-π, π].
- runners: `num_env_runners=0` by default: sampling in the local env runner, in the
  driver process, alternating with the local learner (PPO is synchronous, so a
  remote runner cannot overlap sampling with learning anyway). This is the fair
  setting on a 2-core machine: both sides use the same process layout as our local
  runtime, and nothing pays for moving episodes between processes. `env_runners=1`
  measures one remote runner instead (measured on a busy 2-core VM, 16 envs,
  1024-512 MLPs, batch 4096/256: 912 against 733 env steps/s end to end).
- torch threads: 1 in the driver by default, our runtimes' default
  (`runtime.torch_threads`); with torch's default of 2 on the same busy machine the
  policy's inference was ~10x slower and RLlib's end-to-end figure fell to ~400 steps/s.
- network: RLlib's default PPO module with policy and value MLPs of `hidden` units,
  ReLU, not shared (`vf_share_layers=False`), and a state-independent learned log-std
  (`free_log_std=True`: the policy head outputs the 28 means, as ours does; ours keeps
  the std fixed).
- training: `train_batch_size_per_learner`, `minibatch_size`, `num_epochs=1`, one local
  learner (`num_learners=0`), CPU.

RLlib is an optional extra: `pip install -e .[peer]`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from typing import Any

ENV_ID = "workers.sim.gym_env:MocapHumanoidImitation-v0"  # module prefix: remote runners import it too
MISSING = "RLlib is not installed; the peer benchmark needs it: pip install -e .[peer]"


def import_rllib():
    try:
        import ray
        from ray.rllib.algorithms.ppo import PPOConfig
        from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    except ImportError as e:
        raise ImportError(MISSING) from e
    return ray, PPOConfig, DefaultModelConfig


def build_config(
    num_envs: int,
    hidden: tuple[int, ...],
    train_batch_size: int,
    minibatch_size: int,
    seed: int,
    env_runners: int = 0,
    env_config: dict[str, Any] | None = None,
):
    """RLlib's PPOConfig for the peer comparison (see the module docstring)."""
    import gymnasium

    _, PPOConfig, DefaultModelConfig = import_rllib()
    return (
        PPOConfig()
        .framework("torch")
        .environment(ENV_ID, env_config=dict(env_config or {}))
        .env_runners(
            num_env_runners=env_runners,
            num_envs_per_env_runner=num_envs,
            gym_env_vectorize_mode=gymnasium.VectorizeMode.VECTOR_ENTRY_POINT,
        )
        .learners(num_learners=0, num_gpus_per_learner=0)
        .training(train_batch_size_per_learner=train_batch_size, minibatch_size=minibatch_size, num_epochs=1)
        .rl_module(
            model_config=DefaultModelConfig(
                fcnet_hiddens=list(hidden), fcnet_activation="relu", vf_share_layers=False, free_log_std=True
            )
        )
        .debugging(seed=seed)
    )


def measure_rllib(
    num_envs: int,
    hidden: tuple[int, ...],
    train_batch_size: int,
    minibatch_size: int,
    iterations: int,
    warmup: int,
    seed: int,
    *,
    env_runners: int = 0,
    torch_threads: int | None = 1,
    env_config: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Env steps per second of RLlib's PPO on our humanoid, end to end and sampling only.

    Args:
        num_envs: environments per env runner (one batched simulator).
        hidden: hidden layer sizes of the policy and of the value MLP.
        train_batch_size, minibatch_size: PPO's batch per iteration and SGD minibatch (one epoch).
        iterations: timed `train()` iterations (and `sample()` calls for the sampling figure).
        warmup: untimed `train()` iterations first.
        env_runners: 0 samples in the driver (default); n > 0 uses n remote env runners.
        torch_threads: torch.set_num_threads in the driver (learner, and sampling when local);
            1 by default, as our runtimes (`runtime.torch_threads`); None leaves torch's default.
        env_config: keyword arguments of the environment (clips, sim_hz, control_hz, max_episode_steps, ...).
    """
    if min(num_envs, train_batch_size, minibatch_size, iterations) < 1 or warmup < 0 or env_runners < 0:
        raise ValueError("num_envs, batch sizes and iterations must be at least 1, warmup and env_runners at least 0")
    ray, _, _ = import_rllib()
    import torch

    if torch_threads is not None:
        torch.set_num_threads(torch_threads)
    started_ray = not ray.is_initialized()
    if started_ray:
        ray.init(include_dashboard=False, log_to_driver=False, logging_level="WARNING")
    algo = None
    try:
        config = build_config(num_envs, hidden, train_batch_size, minibatch_size, seed, env_runners, env_config)
        algo = config.build_algo()
        result = None
        for _ in range(warmup):
            result = algo.train()
        steps0 = lifetime_steps(result)  # 0 before the first iteration
        t0 = time.perf_counter()
        for _ in range(iterations):
            result = algo.train()
        train_s = time.perf_counter() - t0
        train_steps = lifetime_steps(result) - steps0
        sample_steps, sample_s = time_sampling(algo, iterations, train_batch_size, env_runners)
    finally:
        if algo is not None:
            algo.stop()
        if started_ray:
            ray.shutdown()
    out = {
        "framework": "rllib",
        "rllib_version": ray.__version__,
        "env_runners": env_runners,
        "vectorization": "vector_entry_point (one BatchedSim per env runner)",
        "num_envs": num_envs,
        "hidden": list(hidden),
        "train_batch_size": train_batch_size,
        "minibatch_size": minibatch_size,
        "num_epochs": 1,
        "iterations": iterations,
        "warmup": warmup,
        "seed": seed,
        "torch_threads": torch.get_num_threads(),
        "cpus": os.cpu_count(),
        "machine": platform.node(),
        "train_env_steps": int(train_steps),
        "train_seconds": train_s,
        "train_steps_per_s": train_steps / train_s,
        "sample_env_steps": int(sample_steps),
        "sample_seconds": sample_s,
        "sample_steps_per_s": sample_steps / sample_s,
    }
    for k in ("train_steps_per_s", "sample_steps_per_s"):
        if not (math.isfinite(out[k]) and out[k] > 0):
            raise RuntimeError(f"RLlib measurement gave {k}={out[k]}")
    return out


def lifetime_steps(result: dict | None) -> float:
    from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

    return float((result or {}).get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0.0))


def time_sampling(algo, calls: int, steps_per_call: int, env_runners: int) -> tuple[int, float]:
    """(steps, seconds) of `calls` env-runner `sample(num_timesteps=steps_per_call)` calls."""

    def sample(runner) -> int:
        return sum(len(e) for e in runner.sample(num_timesteps=steps_per_call, random_actions=False))

    steps = 0
    t0 = time.perf_counter()
    for _ in range(calls):
        if env_runners == 0:
            steps += sample(algo.env_runner)
        else:  # each remote runner samples its share; only the counts come back
            per = max(1, steps_per_call // env_runners)
            counts = algo.env_runner_group.foreach_env_runner(
                lambda r, per=per: sum(len(e) for e in r.sample(num_timesteps=per, random_actions=False)),
                local_env_runner=False,
            )
            steps += sum(counts)
    return steps, time.perf_counter() - t0


def format_table(r: dict[str, Any]) -> str:
    return "\n".join(
        [
            f"RLlib {r['rllib_version']} PPO, {r['env_runners']} remote env runners, {r['num_envs']} envs/runner, "
            f"hidden {r['hidden']}, batch {r['train_batch_size']}/{r['minibatch_size']}, "
            f"torch threads {r['torch_threads']}",
            f"  end to end  {r['train_steps_per_s']:10.1f} env steps/s  ({r['train_env_steps']} steps in "
            f"{r['train_seconds']:.2f} s)",
            f"  sampling    {r['sample_steps_per_s']:10.1f} env steps/s  ({r['sample_env_steps']} steps in "
            f"{r['sample_seconds']:.2f} s)",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m orchestrator.bench.peer_rllib", description=measure_rllib.__doc__)
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--hidden", default="1024,512", help="comma-separated hidden sizes")
    p.add_argument("--batch", type=int, default=4096, help="train batch size")
    p.add_argument("--minibatch", type=int, default=256)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--env-runners", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads in the driver (0: torch's default)")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    hidden = tuple(int(h) for h in a.hidden.split(",") if h)
    r = measure_rllib(
        a.envs, hidden, a.batch, a.minibatch, a.iterations, a.warmup, a.seed, env_runners=a.env_runners,
        torch_threads=a.threads or None,
    )  # fmt: skip
    print(json.dumps(r, indent=2) if a.json else format_table(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
