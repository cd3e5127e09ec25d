"""What a run simulates, from its config: the character, the motion library, the simulator's settings, the seeds.

Every process that needs them (the driver, each rollout worker and learner actor) builds its own
from the config here, so that none depends on the driver's objects:

- `load_character` / `load_library` / `load_character_and_library`: the character's MJCF and the
  clips of `motion`, processed at the control rate (cached on disk by `workers.motion`);
- `sim_config`: the simulator as `sim` says (the character's rates, the terrain, falls detected);
- `evaluation_sim_config`: as evaluation and rendering run it in the driver (each protocol adds its own ends):
  on Warp's CPU device when the driver does not see `sim.device`'s GPU;
- `collection_sim_config`: the simulator as rollout workers collect with it (the loop's termination
  rules and physics threads); a method may change it (`Method.sim_config`);
- `seed_of`: the seed of one part of a run (`offset` names the part), so that parts never share a stream.
"""

from __future__ import annotations

import functools
import sys
from dataclasses import replace

from orchestrator.schema import Config
from workers.body.character import Character
from workers.motion.library import MotionLibrary
from workers.sim.env import SimConfig


def load_character(cfg: Config) -> Character:
    kwargs = {"self_collision": cfg.character.self_collision}
    return Character.load(cfg.character.xml, **kwargs) if cfg.character.xml else Character.load(**kwargs)


def load_library(cfg: Config, character: Character) -> MotionLibrary:
    return MotionLibrary.load(
        character,
        cfg.motion.clips,
        fps=cfg.character.control_hz,
        mirror=cfg.motion.mirror,
        cache_dir=cfg.motion.cache_dir,
        joint_map=dict(cfg.motion.joint_map or {}) or None,
    )


def load_character_and_library(cfg: Config) -> tuple[Character, MotionLibrary]:
    character = load_character(cfg)
    return character, load_library(cfg, character)


def sim_config(cfg: Config) -> SimConfig:
    """The simulator as `sim` says: the character's rates, the terrain, the engine and its device, falls detected."""
    return SimConfig(
        sim_hz=cfg.character.sim_hz,
        control_hz=cfg.character.control_hz,
        terrain=cfg.terrain,
        backend=cfg.sim.backend,
        device=cfg.sim.device,
    )


def evaluation_sim_config(cfg: Config) -> SimConfig:
    """The simulator as evaluation (and rendering, and the model's export) runs it in this process, the driver:
    `sim_config`, but MuJoCo Warp on Warp's CPU device when `sim.device` is a GPU this process does not see (a
    cluster's driver without one; the rollout workers see theirs through Ray), the same engine, slowly."""
    config = sim_config(cfg)
    if config.backend == "warp" and config.device.startswith("cuda") and not _sees_gpu(config.device):
        _say_once(
            f"evaluation: this process sees no GPU for sim.device={config.device}: its MuJoCo Warp simulator runs on "
            "Warp's CPU device (the same physics, slower)"
        )
        return replace(config, device="cpu")
    return config


def _sees_gpu(device: str) -> bool:
    import torch

    return int(device.partition(":")[2] or 0) < torch.cuda.device_count()


@functools.cache
def _say_once(line: str) -> None:
    print(line, file=sys.stderr)


def collection_sim_config(cfg: Config) -> SimConfig:
    """The simulator as the rollout workers run it: the loop's termination rules."""
    loop = cfg.algo.loop
    return replace(
        sim_config(cfg),
        max_episode_steps=loop.max_episode_steps,
        threads=cfg.runtime.sim_threads,
        end_on_fall=loop.end_on_fall,
    )


def seed_of(cfg: Config, offset: int) -> int:
    return cfg.seed * 1000 + offset
