"""`bench offline`: PhysicsVAE's offline updates (the simulation layer's and the VAE's) and the levers on a CPU.

Both learners at a scale's sizes (`--scale`, default cpu: Table 2's networks, batch 256) on one synthetic
batch of body states, as `PhysicsVAEActor`/`SimulationLayerActor` run them. Each lever is measured against the
float32 update with the features computed per batch, in alternating blocks (`--rounds` of `--updates` updates
each; the median of the per-round ratios), since these shared machines drift:

- `features once`: the batch carries s of its states, as the actors now give it (computed once per dataset);
- `bfloat16`: that, under `torch.autocast(dtype=bfloat16)` (`algo.offline.precision=bfloat16`);
- `2 threads`: one update with `torch.set_num_threads(2)`, against one thread;
- `2 at once`: two processes of one thread each, updating at the same time (a sweep's two points with the joblib
  launcher), as updates per second of the machine against one process alone.

Speed only: what bfloat16 does to what the stages learn is the paired study's (docs/physicsvae.md).
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import time
from typing import Any

import torch

LEVERS = ("features once", "bfloat16", "2 threads", "2 at once")


def _learners(scale: str) -> dict[str, Any]:
    """The VAE and the simulation layer at `scale`'s sizes, with one batch each (features per batch and once)."""
    from orchestrator.compose import compose, validate
    from workers.learners.vae import VAEBatch, VAELearner
    from workers.learners.world_model import WorldModelBatch, WorldModelLearner, build_world_model
    from workers.models import body_state

    vae_cfg = validate(compose(["algo=physicsvae", f"scale={scale}", "run_dir=."])).algo.vae
    layer_cfg = validate(compose(["algo=simulation_layer", f"scale={scale}", "run_dir=."])).algo.world_model
    gen = torch.Generator().manual_seed(0)
    out = {}
    for name, n in (("vae", vae_cfg.batch_size), ("world_model", layer_cfg.batch_size)):
        states = torch.randn(n, 2, 15, 13, generator=gen)
        states[..., 3:7] = torch.nn.functional.normalize(states[..., 3:7], dim=-1)
        actions = torch.randn(n, 1, 28, generator=gen)
        features = body_state.features(states)
        if name == "vae":
            layer = build_world_model(15, 28, layer_cfg, 1 / 30)
            learner = VAELearner(15, 28, vae_cfg, layer, 0)
            batches = (VAEBatch(states, actions=actions), VAEBatch(states, actions=actions, features=features))
        else:
            learner = WorldModelLearner(15, 28, 1 / 30, layer_cfg)
            batches = (WorldModelBatch(states, actions), WorldModelBatch(states, actions, features))
        out[name] = (learner, *batches)
    return out


def _block(learner, batch, updates: int, bfloat16: bool = False) -> float:
    """Seconds per update over `updates` updates."""
    t0 = time.perf_counter()
    for _ in range(updates):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bfloat16):
            learner.update(batch)
    return (time.perf_counter() - t0) / updates


def _one_process(scale: str, name: str, updates: int, start, queue) -> None:
    torch.set_num_threads(1)
    learner, _, batch = _learners(scale)[name]
    _block(learner, batch, 2)
    start.wait()
    queue.put(_block(learner, batch, updates))


def _two_at_once(scale: str, name: str, updates: int) -> float:
    """Updates per second of two one-thread processes updating at the same time, together."""
    ctx = mp.get_context("spawn")
    start, queue = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_one_process, args=(scale, name, updates, start, queue)) for _ in range(2)]
    for p in procs:
        p.start()
    seconds = [queue.get() for _ in procs]
    for p in procs:
        p.join()
    return sum(1.0 / s for s in seconds)


def run(scale: str = "cpu", rounds: int = 5, updates: int = 20, learners: tuple[str, ...] = ("vae", "world_model")):
    torch.set_num_threads(1)
    built = _learners(scale)
    rows = []
    for name in learners:
        learner, per_batch, once = built[name]
        for b in (per_batch, once):
            _block(learner, b, 3)
            _block(learner, b, 3, bfloat16=True)
        t: dict[str, list[float]] = {k: [] for k in ("float32", "features once", "bfloat16", "1 thread", "2 threads")}
        alone, together = [], []
        for _ in range(rounds):
            t["float32"].append(_block(learner, per_batch, updates))
            t["features once"].append(_block(learner, once, updates))
            t["bfloat16"].append(_block(learner, once, updates, bfloat16=True))
            t["1 thread"].append(_block(learner, once, updates))
            torch.set_num_threads(2)
            t["2 threads"].append(_block(learner, once, updates))
            torch.set_num_threads(1)
            alone.append(1.0 / _block(learner, once, updates))
            together.append(_two_at_once(scale, name, updates))
        ms = {k: 1e3 * statistics.median(v) for k, v in t.items()}
        ratio = {
            "features once": statistics.median(a / b for a, b in zip(t["float32"], t["features once"], strict=True)),
            "bfloat16": statistics.median(a / b for a, b in zip(t["features once"], t["bfloat16"], strict=True)),
            "2 threads": statistics.median(a / b for a, b in zip(t["1 thread"], t["2 threads"], strict=True)),
            "2 at once": statistics.median(b / a for a, b in zip(alone, together, strict=True)),
        }
        rows.append({"learner": name, "ms": ms, "speedup": ratio, "batch": per_batch.states.shape[0]})
    return {"scale": scale, "rounds": rounds, "updates": updates, "rows": rows}


def format_table(result: dict[str, Any]) -> str:
    lines = [
        f"PhysicsVAE's offline updates at scale={result['scale']}: ms per update (median of {result['rounds']} "
        f"rounds of {result['updates']}), and each lever's speed-up, interleaved",
        "| learner | batch | float32 | features once | bfloat16 | 2 threads | "
        + " | ".join(f"x {k}" for k in LEVERS)
        + " |",
        "| --- " * (6 + len(LEVERS)) + "|",
    ]
    for r in result["rows"]:
        ms, up = r["ms"], r["speedup"]
        cells = [f"{ms[k]:.1f}" for k in ("float32", "features once", "bfloat16", "2 threads")]
        lines.append(f"| {r['learner']} | {r['batch']} | " + " | ".join(cells) + " | "
                     + " | ".join(f"{up[k]:.2f}" for k in LEVERS) + " |")  # fmt: skip
    lines.append("x 2 at once: the machine's updates per second with two one-thread processes, against one alone.")
    return "\n".join(lines)
