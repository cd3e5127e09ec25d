"""The topology a lab runs, on one machine, without Docker: `python -m orchestrator.cluster up|down|status|env`.

    python -m orchestrator.cluster up [--state-dir .cluster] [--json]   # or: make cluster-up
    eval "$(python -m orchestrator.cluster env)"        # the Ray token, the addresses and the MLflow user, for clients
    ray job submit -- python -m orchestrator runtime=ray runtime.address=auto tracking.uri=$MLFLOW_TRACKING_URI
    python -m orchestrator.cluster down                                  # or: make cluster-down

What each command does: `orchestrator.cluster.topology`.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from orchestrator.cluster.topology import (
    DEFAULT_STATE_DIR,
    client_env,
    client_secret_files,
    down,
    load_state,
    print_summary,
    state_path,
    status,
    up,
)
from orchestrator.errors import ServiceError
from orchestrator.tracking.secret_files import private_dir


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.cluster", description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=["up", "down", "status", "env"])
    parser.add_argument("--state-dir", type=Path, default=Path(DEFAULT_STATE_DIR), help="default: ./.cluster")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--head-cpus", type=int, default=2, help="logical CPUs of the Ray head")
    parser.add_argument("--node-cpus", type=int, default=4, help="logical CPUs of each other Ray node")
    parser.add_argument("--nodes", type=int, default=1, help="Ray nodes joining the head")
    parser.add_argument("--object-store-mb", type=int, default=256, help="each Ray node's object store")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds each service has to answer")
    args = parser.parse_args(argv)
    state_dir = args.state_dir.resolve()
    try:
        if args.command == "up":
            private_dir(state_dir)
            state = up(state_dir, args.head_cpus, args.node_cpus, args.nodes, args.object_store_mb, args.timeout)
            print_summary(state, args.json)
        elif args.command == "down":
            if not down(state_dir):
                print(f"nothing to stop: no {state_path(state_dir)}")
        elif args.command == "status":
            info = status(state_dir)
            if args.json:
                print(json.dumps(info, indent=2))
            else:
                for name, value in info["services"].items():
                    print(f"{name:<15} {value}")
            if "down" in info["services"].values():
                return 1
        else:
            state = load_state(state_dir)
            if state is None:
                raise ServiceError(f"no cluster recorded in {state_path(state_dir)}; run `up`")
            for key, value in client_env(state).items():
                print(f"export {key}={shlex.quote(value)}")
            for key, path in client_secret_files(state).items():  # read by the shell that evals this, not printed
                print(f'export {key}="$(cat {shlex.quote(path)})"')
    except ServiceError as e:
        print(f"cluster {args.command}: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"cluster {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
