"""YAML and overrides to a validated `Config`: Hydra composes `conf/`, the schema and the method's own config check it.

- `compose(overrides)`: conf/config.yaml with `overrides`, inside a running Hydra app or not
  (upstream stages, benchmarks and tests compose this way). `algo` is typed by the method's config
  (`Method.config_class`), which conf/algo/<name>.yaml names in its defaults list as `<name>_schema`
  (`register` stores one for each file), so that a key the method does not have is refused there;
- `validate(cfg)`: the composed config as `orchestrator.schema` objects, `algo` as the method's config,
  or a `ConfigError` naming the key of the first bad value;
- `find_method(target)`: the method class that `algo._target_` names, found by its dotted path the
  way Hydra's `_target_` finds any class: no method module is imported here by name.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import fields
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from orchestrator.schema import Config, ConfigError, MethodConfig, sections_of

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def compose(overrides: list[str]) -> Any:
    """conf/config.yaml composed with `overrides` (inside a running Hydra app or not)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register()  # the schema the defaults list starts from
    if GlobalHydra.instance().is_initialized():
        return hydra_compose("config", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose("config", overrides=overrides)


def find_method(target: str) -> type:
    """The class `target` names ("package.module.Class"), if it is a method: it declares its config
    (`config_class`), the upstream stages it `needs` and its `components`."""
    module, _, name = target.rpartition(".")
    cls = getattr(importlib.import_module(module), name, None) if module else None
    if not (isinstance(cls, type) and all(hasattr(cls, a) for a in ("config_class", "needs", "components", "step"))):
        raise TypeError(f"{target} is not a method (a subclass of orchestrator.algos.base.Method)")
    return cls


# The learners' configs name their keys from their own root; here they live under algo.
KEY_ROOTS = {"vae.": "algo.vae.", "world_model.": "algo.world_model.", "task.": "algo.task."}


def full_key(message: str) -> str:
    for short, full in KEY_ROOTS.items():
        if message.startswith(short):
            return full + message[len(short) :]
    return message


def _run_dir_or(default: str, *, _root_: DictConfig) -> str:
    """Hydra's output folder (`hydra.run.dir`): the run directory the command names (`run_dir=...`), so that Hydra's
    own record goes there and nothing into the working directory; else `default` (outputs/<preset>/<time>), which
    is then also the run directory."""
    if "run_dir" in _root_ and not OmegaConf.is_interpolation(_root_, "run_dir") and _root_.run_dir:
        return str(_root_.run_dir)
    return default


def register() -> None:
    OmegaConf.register_new_resolver("run_dir_or", _run_dir_or, replace=True)
    cs = ConfigStore.instance()
    schema = OmegaConf.structured(Config)
    # A map given whole on the command line (`motion.joint_map='{Hips: pelvis}'`) adds keys: open under struct mode.
    OmegaConf.set_struct(schema.motion.joint_map, False)
    cs.store(name="schema", node=schema)
    for path, target in _shipped():  # conf/algo/<name>.yaml's defaults list names <name>_schema
        cs.store(group="algo", name=f"{path.stem}_schema", node=find_method(target).config_class)


def _shipped() -> list[tuple[Path, str]]:
    return [(p, str(OmegaConf.load(p).get("_target_"))) for p in sorted((CONF_DIR / "algo").glob("*.yaml"))]


def shipped_methods() -> set[str]:
    """The `algo._target_` of every method in conf/algo: all that a config read back from a store may name."""
    return {target for _, target in _shipped()}


def _check_finite(node: Any, key: str = "") -> None:
    """ConfigError naming the first key whose value is NaN or infinite (no setting of ours takes one: a
    learning rate of NaN would train on NaN from the first update)."""
    if isinstance(node, dict):
        for k, v in node.items():
            _check_finite(v, f"{key}.{k}" if key else str(k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _check_finite(v, f"{key}[{i}]")
    elif isinstance(node, float) and not math.isfinite(node):
        raise ConfigError(f"{key}: {node} is not a finite number")


def validate(cfg: DictConfig | dict[str, Any], shipped_only: bool = False) -> Config:
    """The composed config as schema objects; raises ConfigError naming the key of a bad value.

    shipped_only: for a config that is not the user's own (read back from a store), `algo._target_` must name
    one of the methods in conf/algo, checked before its module is imported (importing runs the module's code).
    """
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    target = OmegaConf.select(cfg, "algo._target_", default=None)
    if shipped_only and target not in (methods := shipped_methods()):
        raise ConfigError(
            f"algo._target_: {target!r} is not one of the methods in conf/algo ({', '.join(sorted(methods))})"
        )
    method = _method(target)
    algo = cfg.get("algo")
    if isinstance(algo, DictConfig):
        _check_keys(algo, method, former=shipped_only)
    schema = OmegaConf.structured(Config)
    schema.algo = OmegaConf.structured(method.config_class)
    try:
        structured = OmegaConf.merge(schema, cfg)
    except Exception as e:  # OmegaConf's type errors name the full key
        raise ConfigError(str(e)) from None
    _check_finite(OmegaConf.to_container(structured, resolve=True))
    for section in sections_of(method.config_class):
        try:  # the learners' own checks, with the section's key in front
            OmegaConf.to_object(structured.algo[section])
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(_section_key(section, str(e))) from None
    try:
        out = OmegaConf.to_object(structured)
    except ValueError as e:
        raise ConfigError(full_key(str(e))) from None
    _check_needs(out.algo, method)
    check = getattr(method, "check_config", None)  # the method's own rules between its sections
    if check is not None:
        check(out.algo)
    return out


def _check_needs(algo: MethodConfig, method: type) -> None:
    wanted = tuple(getattr(method, "needs", ()))
    for role in algo.needs:
        if role not in wanted:
            has = ", ".join(wanted) or "none"
            raise ConfigError(
                f"algo.needs.{role}: the {algo.name} method does not use a {role} stage (it needs: {has})"
            )
    for role in wanted:
        spec = algo.needs.get(role)
        if not spec or not str(spec).strip():
            raise ConfigError(
                f"algo.needs.{role}: the {algo.name} method needs a {role} stage (a stage such as "
                f"'tracker', or 'run:<run id>')"
            )


def _section_key(section: str, message: str) -> str:
    full = full_key(message)
    return full if full.startswith("algo.") else f"algo.{section}: {message}"


def _method(target: Any) -> type:
    if not target or target == "???":
        raise ConfigError("algo._target_: no method is named (conf/algo/<name>.yaml sets it)")
    try:
        return find_method(str(target))
    except Exception as e:
        raise ConfigError(f"algo._target_: cannot use {target!r} as a method ({e})") from None


def _check_keys(algo: DictConfig, method: type, former: bool) -> None:
    """A key of `algo` (or of `algo.loop`) that the method's config does not have is refused, named; with
    `former` (a config read back from a store), the ones an earlier version wrote are dropped instead: the
    null sections of the methods it did not use and the loop knobs of other methods."""
    config = method.config_class
    loop = {f.name: f for f in fields(config)}["loop"].default_factory()  # type: ignore[misc]
    known_algo, known_loop = {f.name for f in fields(config)}, {f.name for f in fields(loop)}
    who = f"the {algo.get('name')} method ({method.__module__}.{method.__name__})"
    for node, where, known in ((algo, "algo", known_algo), (algo.get("loop"), "algo.loop", known_loop)):
        if not isinstance(node, DictConfig):
            continue
        for key in [k for k in node if k not in known]:
            if former and (where == "algo.loop" or node[key] is None):
                del node[key]
                continue
            if where == "algo.loop":
                raise ConfigError(f"algo.loop.{key}: {who} has no such loop setting")
            inner = next(iter(node[key]), None) if isinstance(node[key], DictConfig) else None
            named = f"algo.{key}" + (f".{inner}" if inner is not None else "")
            has = ", ".join(sections_of(method.config_class)) or "none"
            raise ConfigError(f"{named}: {who} has no {key} section (its sections: {has})")
