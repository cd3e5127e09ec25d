"""The layout: imports go one way, orchestrator -> workers, and there is no import circle, between modules or rooms.

Every `import` and `from ... import` of orchestrator/ and workers/ is read with `ast` (at module level,
inside functions and under `if TYPE_CHECKING:` alike: a circle hidden in a function is still a circle) and
resolved to the project's modules. A room is a top-level module or folder of orchestrator/ or workers/
(`orchestrator/algos/`, `orchestrator/trainer.py`, `workers/sim/`, ...).
"""

from __future__ import annotations

import ast
from pathlib import Path

import orchestrator
import workers

ROOT = Path(orchestrator.__file__).resolve().parents[1]
PACKAGES = ("orchestrator", "workers")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def imports_of(path: Path, name: str, known: set[str]) -> set[str]:
    """The project modules that the module `name` at `path` imports, anywhere in it."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from package (minus level - 1 parts)
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            # `from a import b` imports the module a.b when there is one, else a name of module a.
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:  # `import a.b.c` of a name: the longest module prefix
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = project_modules()
    known = set(modules)
    return {name: imports_of(path, name, known) for name, path in modules.items()}


def room_of(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else parts[0]


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted: the import circles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_circle_finder_finds_a_circle_and_only_circles():
    # a -> b -> c -> a is one circle; d -> a hangs off it; e -> e is a self-import, not a circle of modules.
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert circles(graph) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_the_import_reader_sees_imports_inside_functions_and_type_checking(tmp_path):
    source = (
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from orchestrator.trainer import Trainer\n"
        "def f():\n    from orchestrator import checkpoint\n    import workers.sim.env\n"
    )
    path = tmp_path / "m.py"
    path.write_text(source)
    known = set(project_modules())
    assert imports_of(path, "orchestrator.m", known) == {
        "orchestrator.trainer",
        "orchestrator.checkpoint",
        "workers.sim.env",
    }


def test_no_import_circle_between_modules():
    assert circles(import_graph()) == []


def test_no_import_circle_between_rooms():
    rooms: dict[str, set[str]] = {}
    for module, targets in import_graph().items():
        rooms.setdefault(room_of(module), set()).update(room_of(t) for t in targets if room_of(t) != room_of(module))
    assert circles(rooms) == []


def test_workers_never_import_orchestrator():
    offenders = {m: sorted(t for t in ts if t.startswith("orchestrator")) for m, ts in import_graph().items()}
    assert {m: ts for m, ts in offenders.items() if m.startswith("workers") and ts} == {}


def test_every_module_is_found():
    # The graph covers the whole of both planes (a module the reader missed would hide its circles).
    names = set(project_modules())
    assert {"orchestrator.trainer", "orchestrator.algos.base", "workers.rollout", "workers.sim.env"} <= names
    assert len(names) == sum(1 for pkg in (orchestrator, workers) for _ in Path(pkg.__file__).parent.rglob("*.py"))


def third_party_imports(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def test_only_the_tracking_room_imports_mlflow():
    offenders = [
        name
        for name, path in project_modules().items()
        if "mlflow" in third_party_imports(path) and not name.startswith("orchestrator.tracking")
    ]
    assert offenders == []


def test_no_private_name_is_imported_from_another_module():
    # `from a import _name`: a module's private helper is its own; one that others need gets a public name.
    offenders = []
    for name, path in project_modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in PACKAGES:
                offenders += [f"{name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    assert offenders == []


def test_helpers_live_below_the_commands_that_use_them():
    """Secret files and MLflow's auth app are tracking's (the cluster command and a sweep's server both use them), and
    the loop's counters are the checkpoint's: neither tracking nor the sweep imports the cluster command, and
    preflight does not import the trainer."""
    graph = import_graph()
    below = {m: sorted(t for t in ts if room_of(t) == "orchestrator.cluster") for m, ts in graph.items()}
    assert {
        m: ts for m, ts in below.items() if room_of(m) in ("orchestrator.tracking", "orchestrator.sweep") and ts
    } == {}
    assert "orchestrator.trainer" not in graph["orchestrator.preflight"]


def test_workers_keeps_its_modules_in_rooms():
    """At most 8 loose modules at the top of workers/, and the rollout side (the worker, its policies and recorders,
    PULSE's labels) imports nothing of the evaluation protocols."""
    loose = sorted(p.stem for p in (ROOT / "workers").glob("*.py") if p.stem != "__init__")
    assert len(loose) <= 8, loose
    graph = import_graph()
    for module in ("workers.rollout", "workers.policies", "workers.recorders", "workers.distill"):
        assert not {t for t in graph[module] if t.startswith("workers.evaluation")}, module


def method_configs() -> dict[str, type]:
    """conf/algo/<name>.yaml → the config class of the method it names."""
    from omegaconf import OmegaConf

    from orchestrator.compose import CONF_DIR, find_method

    return {
        p.stem: find_method(str(OmegaConf.load(p)["_target_"])).config_class
        for p in sorted((CONF_DIR / "algo").glob("*.yaml"))
    }


def test_each_method_declares_its_config_once_beside_it_and_its_yaml_names_it():
    """Every method's config is its own class, declared in the method's module; the schema holds no union of them;
    each conf/algo/<name>.yaml starts from its method's schema (`<name>_schema`)."""
    from dataclasses import fields

    from omegaconf import OmegaConf

    import orchestrator.schema as schema
    from orchestrator.compose import CONF_DIR, find_method

    configs = method_configs()
    for name, config in configs.items():
        target = str(OmegaConf.load(CONF_DIR / "algo" / f"{name}.yaml")["_target_"])
        assert config.__module__ == find_method(target).__module__, name
        assert issubclass(config, schema.MethodConfig) and config is not schema.MethodConfig, name
        defaults = OmegaConf.load(CONF_DIR / "algo" / f"{name}.yaml")["defaults"]
        assert list(defaults) == [f"{name}_schema", "_self_"], name
    # One class per method (a variant, the task's PPO trainer, shares its method's).
    assert len(set(configs.values())) == len(configs)
    assert {f.name for f in fields(schema.MethodConfig)} == {"_target_", "name", "loop", "needs"}
    assert not hasattr(schema, "AlgoConfig") and not hasattr(schema, "SECTIONS")


def test_no_method_yaml_restates_a_default_of_its_config():
    """A value in conf/algo/<name>.yaml differs from its config's default: every default is written once."""
    from omegaconf import OmegaConf

    from orchestrator.compose import CONF_DIR

    def restated(given, default, path):
        for key, value in given.items():
            where = f"{path}.{key}" if path else key
            if isinstance(value, dict) and isinstance(default.get(key), dict):
                yield from restated(value, default[key], where)
            elif value == default.get(key, object()):
                yield where

    found = []
    for name, config in method_configs().items():
        given = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "algo" / f"{name}.yaml"))
        given = {k: v for k, v in given.items() if k not in ("defaults", "_target_", "name")}
        found += [f"{name}: {key}" for key in restated(given, OmegaConf.to_container(OmegaConf.structured(config)), "")]
    assert found == []
