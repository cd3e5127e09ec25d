"""Learner benchmark: updates per second and matmul efficiency of each learner's `update(batch)`.

For every learner and size the benchmark builds the learner and one synthetic
but valid batch (random body states with unit quaternions and small velocities,
random actions and observations; timing does not depend on the values), then:

- FLOPs: one update (forward, backward and optimiser step) runs under a
  dispatch mode that records every matmul it dispatches (operator, shapes,
  strides) and counts its FLOPs with the formulas of `torch.utils.flop_counter`
  (those FlopCounterMode uses; FlopCounterMode itself cannot wrap the
  discriminator's update, whose gradient penalty calls `autograd.grad` on a leaf,
  which its module hooks refuse). The count covers mm, addmm, bmm and baddbmm:
  the backward pass, the gradient penalty's double backward and the input
  gradients through frozen networks included; elementwise work (activations,
  layer norms, the optimiser) is not counted.
- updates/s: rounds of one timed `update(batch)` (always the same batch) and
  one timed replay (below), for about `seconds` and at least 3 rounds;
  updates/s = 1 / the median update time. Interleaving the two keeps them under
  the same load when other processes share the machine.
- matmul peak: the replay runs the update's recorded matmuls alone, in order,
  back to back (same operators, shapes, strides, dtype and threads; random
  operands made once), each call timed; peak = FLOPs per update / the median
  replay time. Skinny matmuls (the MoE's gate mixing, 64-wide layers) are slow
  in the replay too, so they are not charged against a big-GEMM ideal.
- achieved GFLOP/s = FLOPs per update × updates/s; share = achieved / peak,
  i.e. the fraction of an update's wall time its matmuls alone take; the rest
  is elementwise work, autograd, the optimiser, Python and dispatch.
- machine peak: one large float32 GEMM (4096² on a GPU, 2048² on the CPU) timed
  on the same device and threads; share of machine = achieved / that, how far
  the update is from what the device can do at its best.

`compile_mode` ("off", "default" or "reduce-overhead", `--compile`): with a mode, each learner's
loss runs through `torch.compile` (`Learner.compile`) after the FLOPs are counted on an eager update;
the first compiled update's time is `compile_s`, and an eager twin (same learner and batch) is timed
in the same rounds for `compiled_over_eager`. The discriminator's loss (a gradient of a gradient)
stays eager.

`device` ("cpu" or "cuda") is where the learners compute (`runtime.learner_device`):
batches start on the CPU, as a replay buffer hands them over, and each update copies
them (pinned, non-blocking); on a GPU every timing synchronises the device first.

Sizes ("paper" are the configs' defaults; "laptop" the learners of each method's laptop scale,
`conf/algo_scale/*_laptop.yaml`, so that the default run's own learners are measured; "small" halves
the widths or more and uses batches of 64 and shorter rollouts):

  learner        paper                                          small
  world_model    MLP 4x512, T_w=8, N_w=512                      4x256, T_w=4, N=64
  vae            MoE 6x(3x512), enc 2x512, z 64, T=24, N=512    6x(3x256), enc 2x256, z 32, T=8, N=64
                 (ControlVAE objective through a 4x512 world model; the small one's is 4x256)
  discriminator  (1024, 512), 256 data + 256 policy             (256, 128), 64 + 64
  ppo            policy and value (1024, 512), minibatch 256    (256, 128), minibatch 64
  task           heading, 3x256, T=16, N=256 on the paper       (128, 64), T=8, N=64 on the small
                 VAE controller and world model                 controller and world model

  laptop         the default run (ControlVAE): world model MLP 3x256, T_w=8, N_w=128; VAE with an MLP
                 policy 2x256, enc 2x256, z 32, T=8, N=64 (Adam) through that world model; AMP's
                 discriminator (512, 256) and PPO (512, 256), minibatch 256; the task policy at the paper's
                 widths, N=128, on the laptop controller (tests/unit/test_bench_learners.py checks these
                 against the composed configs)

The humanoid has 15 bodies and 28 actions; AMP's Φ(s) has 105 features
(`workers.body.features.amp_dim`), which is also the observation size used for PPO.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import torch

from orchestrator.bench.matmuls import CPU, MatmulRecorder, MatmulReplay, machine_peak, sync
from workers.learners.base import Learner, cpu_seeded, resolve_device
from workers.learners.discriminator import DiscriminatorBatch, DiscriminatorConfig, DiscriminatorLearner
from workers.learners.ppo import PPOBatch, PPOConfig, PPOLearner
from workers.learners.task import TaskBatch, TaskConfig, TaskLearner
from workers.learners.vae import ControlVAEObjective, VAEBatch, VAELearner, build_controller
from workers.learners.world_model import WorldModelBatch, WorldModelConfig, WorldModelLearner
from workers.models.world_model import WorldModel

NUM_BODIES, ACTION_DIM, AMP_OBS_DIM, DT = 15, 28, 105, 1.0 / 30.0
LEARNERS = ("world_model", "vae", "discriminator", "ppo", "task")
SIZES = ("paper", "laptop", "small")
ALIASES = {"disc": "discriminator", "wm": "world_model"}
MIN_REPEATS = 3
MAX_REPEATS = 200


@dataclass
class Case:
    learner: Learner
    batch: Any
    description: str


# Synthetic batches ------------------------------------------------------------
def body_states(gen: torch.Generator, *lead: int) -> torch.Tensor:
    """Random body states [*lead, B, 13]: positions around 1 m high, unit quaternions, small velocities."""
    shape = (*lead, NUM_BODIES)
    pos = torch.randn(*shape, 3, generator=gen) * 0.3 + torch.tensor([0.0, 0.0, 1.0])
    quat = torch.randn(*shape, 4, generator=gen)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    lin = torch.randn(*shape, 3, generator=gen) * 0.5
    ang = torch.randn(*shape, 3, generator=gen)
    return torch.cat((pos, quat, lin, ang), dim=-1)


def actions(gen: torch.Generator, *lead: int) -> torch.Tensor:
    return torch.randn(*lead, ACTION_DIM, generator=gen) * 0.3


def frozen_world_model(hidden: tuple[int, ...], gen: torch.Generator) -> WorldModel:
    """A world model of the given width whose normalisers have seen one batch of random transitions."""
    model = WorldModel(NUM_BODIES, ACTION_DIM, hidden, "elu", DT)
    model.observe(body_states(gen, 256), actions(gen, 256), body_states(gen, 256))
    return model


def _size(size: str, **configs: Any) -> Any:
    """The config of `size` among `configs` (paper, laptop, small)."""
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r}; expected one of {SIZES}")
    return configs[size]


# The laptop scale's learners (conf/algo_scale/*_laptop.yaml; a test compares them with the composed configs)
def world_model_config(size: str) -> WorldModelConfig:
    return _size(
        size,
        paper=WorldModelConfig(),
        laptop=WorldModelConfig(hidden=(256,) * 3, lr=1e-3, batch_size=128),
        small=WorldModelConfig(hidden=(256,) * 4, rollout_steps=4, batch_size=64),
    )


def discriminator_config(size: str) -> DiscriminatorConfig:
    return _size(
        size,
        paper=DiscriminatorConfig(),
        laptop=DiscriminatorConfig(hidden=(512, 256)),
        small=DiscriminatorConfig(hidden=(256, 128), batch_size=64),
    )


def ppo_config(size: str) -> PPOConfig:
    laptop = PPOConfig(
        policy_hidden=(512, 256),
        value_hidden=(512, 256),
        optimizer="adam",
        policy_lr=1e-4,
        value_lr=1e-3,
        clip=0.2,
        epochs=5,
    )
    small = PPOConfig(policy_hidden=(256, 128), value_hidden=(256, 128), minibatch_size=64)
    return _size(size, paper=PPOConfig(), laptop=laptop, small=small)


def task_config(size: str) -> TaskConfig:
    small = TaskConfig(hidden=(128, 64), helper_hidden=(64, 64), rollout_steps=8, batch_size=64)
    return _size(size, paper=TaskConfig(), laptop=TaskConfig(batch_size=128), small=small)


# One builder per learner ----------------------------------------------------------
def build_world_model(size: str, gen: torch.Generator, device: torch.device = CPU) -> Case:
    c = world_model_config(size)
    n, t = c.batch_size, c.rollout_steps
    batch = WorldModelBatch(body_states(gen, n, t + 1), actions(gen, n, t))
    learner = WorldModelLearner(NUM_BODIES, ACTION_DIM, DT, c, device)
    return Case(learner, batch, f"MLP {_dims(c.hidden)}, T_w={t}, N_w={n}")


def vae_config(size: str) -> ControlVAEObjective:
    laptop = ControlVAEObjective(
        latent_dim=32,
        encoder_hidden=(256, 256),
        policy="mlp",
        policy_hidden=(256, 256),
        optimizer="adam",
        lr=1e-4,
        batch_size=64,
        rollout_steps=8,
    )
    small = ControlVAEObjective(
        latent_dim=32, encoder_hidden=(256, 256), policy_hidden=(256, 256, 256), rollout_steps=8, batch_size=64
    )
    return _size(size, paper=ControlVAEObjective(), laptop=laptop, small=small)


def _wm_hidden(size: str) -> tuple[int, ...]:
    return world_model_config(size).hidden


def build_vae(size: str, gen: torch.Generator, device: torch.device = CPU) -> Case:
    c = vae_config(size)
    n, t = c.batch_size, c.rollout_steps
    learner = VAELearner(NUM_BODIES, ACTION_DIM, c, frozen_world_model(_wm_hidden(size), gen), device=device)
    batch = VAEBatch(body_states(gen, n, t + 1), reference=body_states(gen, n, t + 1))
    policy = f"MoE {c.num_experts}x({_dims(c.policy_hidden)})" if c.policy == "moe" else f"MLP {_dims(c.policy_hidden)}"
    return Case(learner, batch, f"{policy}, enc {_dims(c.encoder_hidden)}, z {c.latent_dim}, T={t}, N={n}")


def build_discriminator(size: str, gen: torch.Generator, device: torch.device = CPU) -> Case:
    c = discriminator_config(size)
    n, d = c.batch_size, 2 * AMP_OBS_DIM
    batch = DiscriminatorBatch(torch.randn(n, d, generator=gen), torch.randn(n, d, generator=gen))
    learner = DiscriminatorLearner(AMP_OBS_DIM, c, device=device)
    return Case(learner, batch, f"MLP {_dims(c.hidden)}, {n} data + {n} policy")


def build_ppo(size: str, gen: torch.Generator, device: torch.device = CPU) -> Case:
    c = ppo_config(size)
    n = c.minibatch_size
    batch = PPOBatch(
        obs=torch.randn(n, AMP_OBS_DIM, generator=gen),
        actions=actions(gen, n),
        log_probs=torch.randn(n, generator=gen),
        advantages=torch.randn(n, generator=gen),
        returns=torch.randn(n, generator=gen),
        values=torch.randn(n, generator=gen),
    )
    # PPO's minibatches are cut from a rollout already on the device (train_on_rollout moves it once).
    batch = PPOBatch(**{f.name: getattr(batch, f.name).to(device) for f in fields(batch)})
    learner = PPOLearner(AMP_OBS_DIM, ACTION_DIM, c, device)
    return Case(learner, batch, f"pi, V {_dims(c.policy_hidden)}, minibatch {n}")


def build_task(size: str, gen: torch.Generator, device: torch.device = CPU) -> Case:
    c = task_config(size)
    v = vae_config(size)
    controller = build_controller(NUM_BODIES, ACTION_DIM, v)
    learner = TaskLearner(controller, frozen_world_model(_wm_hidden(size), gen), ACTION_DIM, c, device=device)
    n, t = c.batch_size, c.rollout_steps
    if c.task != "heading":  # pragma: no cover - the builder only makes heading batches
        raise ValueError("the task benchmark builds heading goals only")
    heading = (torch.rand(n, t, 1, generator=gen) * 2 - 1) * math.pi
    speed = torch.rand(n, t, 1, generator=gen) * 2.0
    batch = TaskBatch(body_states(gen, n), torch.cat((heading, speed), dim=-1))
    return Case(learner, batch, f"{c.task}, {_dims(c.hidden)} on VAE z {v.latent_dim}, T={t}, N={n}")


BUILDERS: dict[str, Callable[[str, torch.Generator, torch.device], Case]] = {
    "world_model": build_world_model,
    "vae": build_vae,
    "discriminator": build_discriminator,
    "ppo": build_ppo,
    "task": build_task,
}


def _dims(hidden: tuple[int, ...]) -> str:
    return f"{len(hidden)}x{hidden[0]}" if len(set(hidden)) == 1 else "(" + ", ".join(map(str, hidden)) + ")"


# The measurement -------------------------------------------------------------------
COMPILE_MODES = ("off", "default", "reduce-overhead")


def measure(
    case: Case,
    seconds: float,
    machine_gflops: float = float("nan"),
    compile_mode: str = "off",
    eager: Case | None = None,
) -> dict[str, Any]:
    """FLOPs, updates/s, achieved and peak matmul rates of one learner at one size. With `compile_mode` other
    than "off" the FLOPs are counted on an eager update, then the loss is compiled (`Learner.compile`), the
    first compiled update timed as `compile_s`, and the compiled updates timed; given `eager`, the same learner
    and batch left eager, its updates are timed in the same rounds, alternating with the compiled ones."""
    learner, batch = case.learner, case.batch
    device = learner.device
    recorder = MatmulRecorder()
    t0 = time.perf_counter()
    with recorder:
        learner.update(batch)
    sync(device)
    first = time.perf_counter() - t0
    flops = recorder.flops
    replay = MatmulReplay(recorder, device=device)
    compile_s = float("nan")
    if compile_mode != "off":
        learner.compile(None if compile_mode == "default" else compile_mode)
        t0 = time.perf_counter()
        learner.update(batch)
        sync(device)
        compile_s = time.perf_counter() - t0
        learner.update(batch)  # CUDA graphs are recorded on the calls after the first
    if (
        first < 0.25 * seconds or device.type == "cuda" or compile_mode != "off"
    ):  # one more warm-up round when it is cheap
        learner.update(batch)
        replay.run()
    if eager is not None:
        eager.learner.update(eager.batch)
    updates: list[float] = []
    passes: list[float] = []
    eager_updates: list[float] = []
    end = time.perf_counter() + seconds * (1 if eager is None else 2)
    while len(updates) < MIN_REPEATS or (time.perf_counter() < end and len(updates) < MAX_REPEATS):
        sides = [(learner, batch, updates)] + ([] if eager is None else [(eager.learner, eager.batch, eager_updates)])
        for one, its_batch, times in sides if len(updates) % 2 else sides[::-1]:  # alternating which goes first
            sync(device)
            t0 = time.perf_counter()
            one.update(its_batch)
            sync(device)
            times.append(time.perf_counter() - t0)
        passes.append(replay.run())
    median, matmul_s = statistics.median(updates), statistics.median(passes)
    eager_rate = 1.0 / statistics.median(eager_updates) if eager_updates else float("nan")
    achieved = flops / median
    peak = flops / matmul_s if matmul_s > 0 else float("nan")
    return {
        "description": case.description,
        "repeats": len(updates),
        "update_s_median": median,
        "update_s_min": min(updates),
        "updates_per_s": 1.0 / median,
        "flops_per_update": flops,
        "gflop_per_update": flops / 1e9,
        "achieved_gflops_per_s": achieved / 1e9,
        "matmul_peak_gflops_per_s": peak / 1e9,
        "share_of_peak": achieved / peak if flops else float("nan"),
        "machine_peak_gflops_per_s": machine_gflops,
        "share_of_machine_peak": achieved / 1e9 / machine_gflops if flops else float("nan"),
        "matmul_s_median": matmul_s,
        "recorded_update_s": first,
        "compiled": None if compile_mode == "off" else compile_mode,
        "compile_s": compile_s,
        "eager_updates_per_s": eager_rate,  # the eager twin's, in the same rounds (compiled runs only)
        "compiled_over_eager": eager_rate and (1.0 / median) / eager_rate,
        "matmul_calls_per_update": len(recorder.order),
        "distinct_matmuls": len(recorder.calls),
        "top_matmuls": replay.top(5),
    }


def parse_names(text: str | None, allowed: tuple[str, ...], what: str) -> list[str]:
    """A comma-separated subset of `allowed` (aliases accepted), in the given order; all when empty."""
    if not text:
        return list(allowed)
    names = [ALIASES.get(n.strip(), n.strip()) for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in allowed]
    if unknown:
        raise ValueError(f"unknown {what} {', '.join(unknown)}; expected some of {', '.join(allowed)}")
    return list(dict.fromkeys(names))


def _build(name: str, size: str, seed: int, device: torch.device) -> Case:
    with cpu_seeded(seed):
        return BUILDERS[name](size, torch.Generator().manual_seed(seed), device)


def run(
    learners: list[str] | None = None,
    sizes: list[str] | None = None,
    seconds: float = 5.0,
    threads: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    device: str = "cpu",
    compile_mode: str = "off",
) -> dict[str, Any]:
    """Every learner at every size on `device` ("cpu" or "cuda": a DeviceError when there is no GPU), with the
    losses compiled unless `compile_mode` is "off" (the discriminator's, which torch.compile cannot take,
    stays eager and says so)."""
    if compile_mode not in COMPILE_MODES:
        raise ValueError(f"--compile: unknown mode {compile_mode!r}; expected one of {COMPILE_MODES}")
    dev = resolve_device(device, "--device")
    learners = list(learners or LEARNERS)
    sizes = list(sizes or SIZES)
    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    wall0 = time.perf_counter()
    results = []
    try:
        if progress:
            progress(f"machine peak on {dev} ...")
        peak = machine_peak(dev)
        for name in learners:
            for size in sizes:
                if progress:
                    progress(f"{name} ({size}) ...")
                case = _build(name, size, seed, dev)
                mode = "off" if case.learner.double_backward else compile_mode
                twin = _build(name, size, seed, dev) if mode != "off" else None  # left eager, same rounds
                with torch.random.fork_rng(devices=[]):
                    results.append({"learner": name, "size": size, **measure(case, seconds, peak, mode, twin)})
        used = torch.get_num_threads()
    finally:
        torch.set_num_threads(previous)
    return {
        "benchmark": "learners",
        "machine": {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "versions": {"torch": torch.__version__},
        "device": str(dev) + (f" ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else ""),
        "machine_peak_gflops_per_s": peak,
        "threads": used,
        "seconds_per_measurement": seconds,
        "compile": compile_mode,
        "wall_s": time.perf_counter() - wall0,
        "results": results,
    }


def format_table(r: dict[str, Any]) -> str:
    lines = [
        f"learner benchmark on {r['device']}: {r['threads']} torch thread(s), about "
        f"{r['seconds_per_measurement']:g} s per measurement, {r['wall_s']:.0f} s in all; machine peak "
        f"{r['machine_peak_gflops_per_s']:.0f} GFLOP/s (one large float32 GEMM); losses compiled: {r['compile']}",
        f"{'learner':<14}{'size':<7}{'updates/s':>10}{'reps':>6}{'GFLOP/upd':>11}{'GFLOP/s':>9}"
        f"{'mm peak GFLOP/s':>17}{'share':>7}{'of machine':>11}  sizes",
    ]
    for x in r["results"]:
        lines.append(
            f"{x['learner']:<14}{x['size']:<7}{x['updates_per_s']:>10.2f}{x['repeats']:>6}"
            f"{x['gflop_per_update']:>11.3f}{x['achieved_gflops_per_s']:>9.1f}"
            f"{x['matmul_peak_gflops_per_s']:>17.1f}{x['share_of_peak']:>7.2f}{x['share_of_machine_peak']:>11.3f}"
            f"  {x['description']}" + (_compiled_note(x) if x["compiled"] else "")
        )
    lines.append(
        "GFLOP/upd: matmul FLOPs of one update, forward and backward (torch.utils.flop_counter's formulas); "
        "mm peak: the same matmuls replayed alone; share = achieved / mm peak; of machine = achieved / machine "
        "peak; reps: timed rounds (medians)."
    )
    return "\n".join(lines)


def _compiled_note(x: dict[str, Any]) -> str:
    return (
        f"; compiled ({x['compiled']}) in {x['compile_s']:.0f} s, {x['compiled_over_eager']:.2f}x eager "
        f"({x['eager_updates_per_s']:.2f}/s in the same rounds)"
    )
