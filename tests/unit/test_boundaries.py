"""workers/ is the data plane: it never imports ray, mlflow or hydra."""

import ast
import subprocess
import sys
from pathlib import Path

import workers

FORBIDDEN = {"ray", "mlflow", "hydra", "omegaconf"}
WORKERS = Path(workers.__file__).parent


def test_no_forbidden_imports_in_source():
    offenders = []
    for path in WORKERS.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            offenders += [f"{path.name}: {n}" for n in names if n.split(".")[0] in FORBIDDEN]
    assert not offenders


def test_importing_every_worker_module_loads_none_of_them():
    modules = sorted(
        ".".join(p.relative_to(WORKERS.parent).with_suffix("").parts)
        for p in WORKERS.rglob("*.py")
        if p.name != "__init__.py"
    )
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {sorted(FORBIDDEN)!r})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == ""
