"""Command line of the benchmarks."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.bench", description=__doc__)
    sub = parser.add_subparsers(dest="what", required=True)
    sim = sub.add_parser("sim", help="raw MuJoCo stepping against the batched simulator")
    sim.add_argument("--envs", type=int, default=32, help="environments in the batched simulator")
    sim.add_argument("--seconds", type=float, default=10.0, help="wall time of each policy's measurement per rate")
    sim.add_argument("--block-seconds", type=float, default=0.25, help="each raw or batched block; pairs alternate")
    sim.add_argument("--sim-hz", default="480", help="comma-separated physics rates, e.g. 480,240,120")
    sim.add_argument("--control-hz", type=float, default=30.0)
    sim.add_argument("--threads", type=int, default=1, help="threads stepping the batched simulator")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--backend", default="mujoco", choices=("mujoco", "warp"), help="warp: MuJoCo Warp against C")
    sim.add_argument("--device", default="cuda", help="warp: the Warp device (cuda, cuda:N or cpu)")
    sim.add_argument("--worlds", default="1024,4096,16384", help="warp: comma-separated world counts")
    sim.add_argument("--cpu-envs", type=int, default=256, help="warp: MuJoCo C environments it is compared with")
    sim.add_argument("--cpu-threads", type=int, help="warp: threads of the MuJoCo C side (default: every core)")
    learners = sub.add_parser("learners", help="each learner's update(batch): updates/s and share of matmul peak")
    learners.add_argument("--learners", help="comma-separated subset of world_model,vae,discriminator,ppo,task")
    learners.add_argument("--sizes", help="comma-separated subset of paper,laptop,small")
    learners.add_argument("--seconds", type=float, default=5.0, help="time budget of each measurement")
    learners.add_argument("--threads", type=int, help="torch.set_num_threads (default: torch's default)")
    learners.add_argument("--seed", type=int, default=0)
    learners.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the learners compute")
    learners.add_argument(
        "--compile",
        default="off",
        choices=("off", "default", "reduce-overhead"),
        help="time the updates with each loss through torch.compile in this mode (the discriminator's stays eager)",
    )
    device = sub.add_parser("device", help="the GPU check: learners and a paper-size iteration on cuda and cpu")
    device.add_argument("--devices", default="cuda,cpu", help="comma-separated subset of cuda,cpu")
    device.add_argument("--seconds", type=float, default=3.0, help="time budget of each learner measurement")
    device.add_argument("--threads", type=int, help="torch.set_num_threads for the CPU (default: torch's default)")
    device.add_argument(
        "--compile",
        default="reduce-overhead",
        choices=("off", "default", "reduce-overhead"),
        help="on the GPU, the learners again with their losses compiled in this mode",
    )
    device.add_argument(
        "--compile-sizes", default="small", help="comma-separated sizes compiled on the GPU (paper takes minutes)"
    )
    pipeline = sub.add_parser("pipeline", help="end-to-end samples/s and updates/s, local against Ray")
    pipeline.add_argument("--algos", default="controlvae,amp,tracker", help="comma-separated methods (conf/algo/)")
    pipeline.add_argument("--scale", default="smoke", help="the scale of every method's sizes (conf/scale/)")
    pipeline.add_argument("--runtimes", default="local,ray", help="comma-separated subset of local,ray")
    pipeline.add_argument("--workers", default="1,2", help="comma-separated rollout worker counts")
    pipeline.add_argument("--iterations", type=int, default=20, help="timed loop iterations per measurement")
    pipeline.add_argument("--warmup", type=int, default=3, help="untimed iterations first")
    pipeline.add_argument("--envs", type=int, default=16, help="environments per rollout worker")
    pipeline.add_argument("--seed", type=int, default=0)
    pipeline.add_argument("--sim", default="mujoco", help="comma-separated simulator engines: mujoco,warp")
    pipeline.add_argument("--sim-device", default="cuda", help="the warp engine's device (cuda, cuda:N or cpu)")
    rollout = sub.add_parser("rollout", help="the rollout worker with each policy against raw mj_step, interleaved")
    rollout.add_argument(
        "--policies", default="vae,actor-critic", help="comma-separated: vae,vae-paper,actor-critic,tracker,task"
    )
    rollout.add_argument("--envs", type=int, default=32, help="environments of the worker")
    rollout.add_argument("--seconds", type=float, default=10.0, help="interleaved time per policy and rate")
    rollout.add_argument("--block-seconds", type=float, default=0.5, help="each raw or worker block")
    rollout.add_argument("--sim-hz", default="480", help="comma-separated physics rates")
    rollout.add_argument("--control-hz", type=float, default=30.0)
    rollout.add_argument("--collect", type=int, default=16, help="control steps per collect call")
    rollout.add_argument("--threads", type=int, default=1, help="threads stepping the batched simulator")
    rollout.add_argument("--seed", type=int, default=0)
    host = sub.add_parser("host", help="a rollout worker's work besides the physics, per control step (no physics)")
    host.add_argument(
        "--policies", default="vae,tracker", help="comma-separated: vae,vae-paper,actor-critic,tracker,task"
    )
    host.add_argument("--envs", default="1024,4096", help="comma-separated environment counts of the worker")
    host.add_argument("--steps", type=int, default=32, help="timed control steps per measurement")
    host.add_argument("--collect", type=int, default=8, help="control steps per collect call")
    host.add_argument("--device", default="cpu", help="where the policy's inference runs (cpu, cuda or cuda:N)")
    host.add_argument(
        "--sim", default="mujoco", help="comma-separated frozen engines: mujoco (host), warp (on --device; the extra)"
    )
    host.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (a worker's default: 1)")
    host.add_argument("--seed", type=int, default=0)
    peer = sub.add_parser("peer", help="our tracker pipeline against RLlib's PPO, interleaved (needs .[peer])")
    peer.add_argument("--envs", type=int, default=16, help="environments stepped as one batch, each side")
    peer.add_argument("--hidden", default="1024,512", help="policy and value MLP sizes (AMP's)")
    peer.add_argument("--batch", type=int, default=4096, help="environment steps per PPO iteration (AMP: 4096)")
    peer.add_argument("--minibatch", type=int, default=256, help="SGD minibatch (AMP: 256)")
    peer.add_argument("--rounds", type=int, default=5, help="interleaved timed rounds")
    peer.add_argument("--warmup", type=int, default=1, help="untimed iterations of each side first")
    peer.add_argument("--seed", type=int, default=0)
    peer.add_argument("--ours", default="ray", choices=("local", "ray"), help="our runtime")
    peer.add_argument("--workers", type=int, default=2, help="our rollout workers (the envs are split among them)")
    peer.add_argument("--overlap", action="store_true", help="ours: collect the next batch while PPO trains")
    peer.add_argument("--sim-threads", type=int, default=1, help="ours: threads stepping each worker's simulator")
    learning = sub.add_parser("learning", help="the default run's seconds and samples until it tracks and stays up")
    learning.add_argument("--minutes", type=float, default=30.0, help="training wall time (evaluations not counted)")
    learning.add_argument("--eval-every", type=float, default=120.0, help="training seconds between evaluations")
    learning.add_argument("--fall-rollouts", type=int, default=32, help="time-until-fall rollouts per evaluation")
    learning.add_argument("--figure", type=Path, help="where the figure goes (default: outputs/bench/learning-*.png)")
    learning.add_argument("overrides", nargs="*", help="Hydra overrides of the default run, e.g. seed=1")
    chaos = sub.add_parser("chaos", help="a Ray run with killed actors and a tracking outage: recovered, nothing lost")
    chaos.add_argument("--minutes", type=float, default=6.0, help="training wall time (algo.loop.max_minutes)")
    chaos.add_argument("--kill-every", type=float, default=60.0, help="seconds between rollout worker kills")
    chaos.add_argument("--outage", type=float, help="seconds the tracking server is down (default: min(180, 20 x M))")
    chaos.add_argument("--run-dir", type=Path, help="where the run and the server's store go (default: outputs/bench/)")
    chaos.add_argument("overrides", nargs="*", help="Hydra overrides of the run, e.g. runtime.rollout_workers=3")
    offline = sub.add_parser(
        "offline", help="PhysicsVAE's offline updates: bfloat16, features once, threads, 2 at once"
    )
    offline.add_argument("--scale", default="cpu", help="the sizes of algo_scale/physicsvae_<scale> and world_model_")
    offline.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    offline.add_argument("--updates", type=int, default=20, help="updates per block")
    offline.add_argument("--learners", default="vae,world_model", help="comma-separated subset of vae,world_model")
    for p in (sim, learners, device, pipeline, rollout, host, peer, learning, chaos, offline):
        p.add_argument("--json", action="store_true", help="print JSON instead of the table")
        p.add_argument("--out", type=Path, help="also write the JSON to this file")
    args = parser.parse_args(argv)

    if args.what == "sim" and args.backend == "warp":
        text, result = _bench_warp(parser, args)
    elif args.what == "sim":
        from orchestrator.bench import sim as bench_sim

        try:
            rates = [float(hz) for hz in args.sim_hz.split(",") if hz]
        except ValueError:
            parser.error(f"--sim-hz: expected numbers, got {args.sim_hz}")
        if not rates or min(rates) <= 0:
            parser.error("--sim-hz: expected positive rates")
        if args.envs < 1 or args.seconds <= 0 or args.block_seconds <= 0 or args.threads < 1:
            parser.error("--envs and --threads must be at least 1, --seconds and --block-seconds positive")
        result = bench_sim.run(
            args.envs, args.seconds, rates, args.control_hz, args.seed, args.block_seconds, args.threads
        )
        text = bench_sim.format_table(result)
    elif args.what == "learners":
        from orchestrator.bench import learners as bench_learners

        try:
            names = bench_learners.parse_names(args.learners, bench_learners.LEARNERS, "learner")
            sizes = bench_learners.parse_names(args.sizes, bench_learners.SIZES, "size")
        except ValueError as e:
            parser.error(str(e))
        if args.seconds <= 0 or (args.threads is not None and args.threads < 1):
            parser.error("--seconds must be positive and --threads at least 1")
        from workers.learners.base import DeviceError

        try:
            result = bench_learners.run(
                names,
                sizes,
                args.seconds,
                args.threads,
                args.seed,
                lambda m: print(m, file=sys.stderr),
                args.device,
                args.compile,
            )
        except DeviceError as e:
            parser.exit(2, f"error: {e}\n")
        text = bench_learners.format_table(result)
    elif args.what == "device":
        from orchestrator.bench import device as bench_device
        from workers.learners.base import DeviceError

        devices = [d for d in args.devices.split(",") if d]
        if not devices or not set(devices) <= {"cpu", "cuda"}:
            parser.error(f"--devices: expected cuda and/or cpu, got {args.devices}")
        learners = bench_device.bench_learners
        try:
            compile_sizes = tuple(learners.parse_names(args.compile_sizes, learners.SIZES, "size"))
        except ValueError as e:
            parser.error(f"--compile-sizes: {e}")
        try:
            result = bench_device.run(
                devices,
                args.seconds,
                args.threads,
                lambda m: print(m, file=sys.stderr),
                args.compile,
                compile_sizes,
            )
        except DeviceError as e:
            parser.exit(2, f"error: {e}\n")
        text = bench_device.format_report(result)
    elif args.what == "pipeline":
        from orchestrator.bench import pipeline as bench_pipeline

        runtimes = [r for r in args.runtimes.split(",") if r]
        if not set(runtimes) <= {"local", "ray"}:
            parser.error(f"--runtimes: expected local and/or ray, got {args.runtimes}")
        try:
            workers = [int(w) for w in args.workers.split(",") if w]
        except ValueError:
            parser.error(f"--workers: expected integers, got {args.workers}")
        if not workers or min(workers) < 1 or args.iterations < 1 or args.envs < 1:
            parser.error("--workers, --iterations and --envs must be at least 1")
        algos = [a for a in args.algos.split(",") if a]
        sims = tuple(s for s in args.sim.split(",") if s)
        if not sims or not set(sims) <= {"mujoco", "warp"}:
            parser.error(f"--sim: expected mujoco and/or warp, got {args.sim}")
        if "warp" in sims:
            _refuse_missing_warp(parser, "--sim-device", args.sim_device)
        result = bench_pipeline.run(
            algos,
            args.scale,
            runtimes,
            workers,
            args.iterations,
            args.warmup,
            args.envs,
            args.seed,
            lambda m: print(m, file=sys.stderr),
            sims,
            args.sim_device,
        )
        text = bench_pipeline.format_table(result)
    elif args.what == "rollout":
        from orchestrator.bench import rollout as bench_rollout

        policies = [p for p in args.policies.split(",") if p]
        if not set(policies) <= set(bench_rollout.POLICIES) or not policies:
            parser.error(f"--policies: expected some of {','.join(bench_rollout.POLICIES)}, got {args.policies}")
        try:
            rates = [float(hz) for hz in args.sim_hz.split(",") if hz]
        except ValueError:
            parser.error(f"--sim-hz: expected numbers, got {args.sim_hz}")
        if min(args.envs, args.collect, args.threads) < 1 or args.seconds <= 0 or args.block_seconds <= 0:
            parser.error("--envs, --collect and --threads must be at least 1, --seconds and --block-seconds positive")
        result = bench_rollout.run(
            policies, args.envs, args.seconds, rates, args.control_hz, args.collect, args.seed, args.block_seconds,
            args.threads,
        )  # fmt: skip
        text = bench_rollout.format_table(result)
    elif args.what == "host":
        text, result = _bench_host(parser, args)
    elif args.what == "peer":
        from orchestrator.bench import peer as bench_peer

        try:
            hidden = tuple(int(h) for h in args.hidden.split(",") if h)
        except ValueError:
            parser.error(f"--hidden: expected integers, got {args.hidden}")
        if min(args.envs, args.batch, args.minibatch, args.rounds) < 1 or args.warmup < 0 or not hidden:
            parser.error("--envs, --batch, --minibatch and --rounds must be at least 1, --warmup non-negative")
        try:
            result = bench_peer.run(
                args.envs, hidden, args.batch, args.minibatch, args.rounds, args.warmup, args.seed,
                args.ours, args.workers, args.overlap, sim_threads=args.sim_threads,
            )  # fmt: skip
        except ImportError as e:
            print(e, file=sys.stderr)
            return 2
        text = bench_peer.format_table(result)
    elif args.what == "offline":
        from orchestrator.bench import offline as bench_offline

        names = tuple(n for n in args.learners.split(",") if n)
        if not names or set(names) - {"vae", "world_model"} or args.rounds < 1 or args.updates < 1:
            parser.error("--learners: a subset of vae,world_model; --rounds and --updates at least 1")
        result = bench_offline.run(args.scale, args.rounds, args.updates, names)
        text = bench_offline.format_table(result)
    elif args.what == "learning":
        import time

        from orchestrator.bench import learning as bench_learning

        if args.minutes <= 0 or args.eval_every <= 0 or args.fall_rollouts < 1:
            parser.error("--minutes and --eval-every must be positive, --fall-rollouts at least 1")
        result = bench_learning.run(
            args.minutes, args.eval_every, args.fall_rollouts, args.overrides, lambda m: print(m, file=sys.stderr)
        )
        figure = args.figure or Path("outputs/bench") / f"learning-{time.strftime('%Y-%m-%d_%H-%M-%S')}.png"
        bench_learning.plot(result, figure)
        result["figure"] = str(figure)
        text = bench_learning.format_table(result)
    elif args.what == "chaos":
        import time

        from orchestrator.bench import chaos as bench_chaos

        if args.minutes <= 0 or args.kill_every <= 0 or (args.outage is not None and args.outage <= 0):
            parser.error("--minutes, --kill-every and --outage must be positive")
        run_dir = args.run_dir or Path("outputs/bench") / f"chaos-{time.strftime('%Y-%m-%d_%H-%M-%S')}"
        result = bench_chaos.run(
            args.minutes, args.kill_every, args.outage, run_dir, args.overrides, lambda m: print(m, file=sys.stderr)
        )
        text = bench_chaos.format_table(result)
    else:  # pragma: no cover - argparse refuses unknown commands
        parser.error(f"unknown benchmark {args.what}")

    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2) if args.json else text)
    if args.what == "chaos" and not bench_chaos.passed(result):
        return 1  # a fault not recovered, a metric lost, or the run did not finish
    return 0


def _refuse_missing_warp(parser: argparse.ArgumentParser, flag: str, device: str) -> None:
    """Exit 2 with one line when the warp extra is missing or `device` is a GPU this machine does not have."""
    from workers.sim.warp_physics import INSTALL_HINT, warp_available

    if not warp_available():
        parser.exit(2, f"error: the warp simulator needs mujoco-warp and warp-lang: {INSTALL_HINT}\n")
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            parser.exit(
                2,
                f"error: {flag} {device}: this machine has no CUDA GPU ({flag} cpu runs Warp's CPU kernels, slowly)\n",
            )


def _bench_host(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[str, dict]:
    """`bench host`: refusals in one line before anything is built, then the benchmark."""
    from orchestrator.bench import host as bench_host

    policies = [p for p in args.policies.split(",") if p]
    if not policies or not set(policies) <= set(bench_host.POLICIES):
        parser.error(f"--policies: expected some of {','.join(bench_host.POLICIES)}, got {args.policies}")
    try:
        envs = [int(n) for n in args.envs.split(",") if n]
    except ValueError:
        parser.error(f"--envs: expected integers, got {args.envs}")
    if not envs or min(envs + [args.steps, args.collect, args.threads]) < 1:
        parser.error("--envs, --steps, --collect and --threads must be at least 1")
    if args.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            parser.exit(2, f"error: --device {args.device}: this machine has no CUDA GPU\n")
    elif args.device != "cpu":
        parser.error(f"--device: expected cpu, cuda or cuda:N, got {args.device}")
    sims = tuple(s for s in args.sim.split(",") if s)
    if not sims or not set(sims) <= set(bench_host.SIMS):
        parser.error(f"--sim: expected some of {','.join(bench_host.SIMS)}, got {args.sim}")
    if "warp" in sims:
        from workers.sim.warp_physics import INSTALL_HINT, warp_available

        if not warp_available():
            parser.exit(2, f"error: --sim warp needs mujoco-warp and warp-lang: {INSTALL_HINT}\n")
    result = bench_host.run(policies, envs, args.steps, args.collect, args.device, args.threads, args.seed, sims)
    return bench_host.format_table(result), result


def _bench_warp(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[str, dict]:
    """`bench sim --backend warp`: refusals in one line before anything is built, then the benchmark."""

    try:
        worlds = [int(n) for n in args.worlds.split(",") if n]
    except ValueError:
        parser.error(f"--worlds: expected integers, got {args.worlds}")
    if not worlds or min(worlds) < 1 or args.cpu_envs < 1 or (args.cpu_threads is not None and args.cpu_threads < 1):
        parser.error("--worlds, --cpu-envs and --cpu-threads must be at least 1")
    if args.seconds <= 0 or args.block_seconds <= 0:
        parser.error("--seconds and --block-seconds must be positive")
    rates = [float(hz) for hz in args.sim_hz.split(",") if hz]
    if len(rates) != 1:
        parser.error("--sim-hz: the warp benchmark takes one rate")
    _refuse_missing_warp(parser, "--device", args.device)
    from orchestrator.bench import warp_sim

    result = warp_sim.run(
        worlds,
        args.device,
        args.seconds,
        args.block_seconds,
        rates[0],
        args.control_hz,
        args.seed,
        args.cpu_envs,
        args.cpu_threads,
    )
    return warp_sim.format_table(result), result


if __name__ == "__main__":
    sys.exit(main())
