"""A ControlVAE controller trained on one simulator engine, evaluated on both (issue 25, item 3; docs/warp.md).

    python scripts/warp_transfer.py RUN_DIR [RUN_DIR ...] [--eval-seeds 5] [--device cpu] [overrides ...]

Each RUN_DIR is a finished default-loop run (its `weights/controller.pt`, the controller's plain tensors) composed
with the given overrides (those it was trained with, e.g. motion=walk). For every run and every evaluation seed, the
run's evaluation protocols (`eval.*`: time until fall from the first clip's start, tracking error over the clips'
segments) run on MuJoCo C and on MuJoCo Warp from the same starts. The report gives, per run and engine, the mean
over evaluation seeds and the seeds' standard deviation, and the engine difference (Warp - C) beside that spread:
the same policy should score the same on both within the spread of its own evaluation seeds.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from orchestrator.compose import compose, validate
from orchestrator.world import evaluation_sim_config, load_character_and_library
from workers.evaluation.controller import time_until_fall, tracking_error
from workers.learners.vae import build_controller


def load_controller(run_dir: Path, character, cfg):
    state = torch.load(run_dir / "weights" / "controller.pt", weights_only=True)
    prefix = "controller."
    controller = build_controller(character.num_bodies, character.num_actions, cfg.algo.vae)
    controller.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})
    return controller.eval()


def evaluate(controller, character, library, cfg, sim_config, seed: int) -> dict[str, float]:
    e = cfg.eval
    fall = time_until_fall(
        controller, character, library, e.fall_rollouts, e.fall_max_seconds, sim_config=sim_config, seed=seed
    )
    track = tracking_error(controller, character, library, e.tracking_seconds, sim_config=sim_config, seed=seed)
    return {"time_until_fall": fall["mean"], "tracking_error": track["mean"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories, then Hydra overrides (key=value)")
    parser.add_argument("--eval-seeds", type=int, default=5)
    parser.add_argument("--device", default="cpu", help="the Warp device")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    runs = [Path(r) for r in args.runs if "=" not in r]
    overrides = [r for r in args.runs if "=" in r]
    cfg = validate(compose(["run_dir=.", *overrides]))
    character, library = load_character_and_library(cfg)
    engines = {
        "mujoco": evaluation_sim_config(cfg),
        "warp": replace(evaluation_sim_config(cfg), backend="warp", device=args.device),
    }
    report = []
    for run in runs:
        controller = load_controller(run, character, cfg)
        scores = {
            name: [evaluate(controller, character, library, cfg, sc, s) for s in range(args.eval_seeds)]
            for name, sc in engines.items()
        }
        row = {"run": str(run)}
        for metric in ("time_until_fall", "tracking_error"):
            for name in engines:
                values = np.array([x[metric] for x in scores[name]])
                row[f"{metric}_{name}"] = float(values.mean())
                row[f"{metric}_{name}_std"] = float(values.std(ddof=1)) if len(values) > 1 else 0.0
            row[f"{metric}_difference"] = row[f"{metric}_warp"] - row[f"{metric}_mujoco"]
        report.append(row)
        fall = {e: f"{row[f'time_until_fall_{e}']:.2f} ± {row[f'time_until_fall_{e}_std']:.2f} s" for e in engines}
        track = {e: f"{row[f'tracking_error_{e}']:.4f} ± {row[f'tracking_error_{e}_std']:.4f} m" for e in engines}
        print(
            f"{run}: time until fall C {fall['mujoco']}, Warp {fall['warp']}; tracking error C {track['mujoco']}, "
            f"Warp {track['warp']} ({args.eval_seeds} evaluation seeds each, ± their standard deviation)",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps({"eval": dict(cfg.eval.__dict__), "runs": report}, indent=2))


if __name__ == "__main__":
    main()
