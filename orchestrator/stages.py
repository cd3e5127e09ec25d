"""Stages: runs of methods that feed each other through MLflow artifacts, reused when identical.

A method names the stages it needs in `algo.needs`, role → spec (conf/algo/*.yaml):

    needs: {demos: demos, world_model: simulation_layer}

A spec is either a stage, "<algo> [key=value ...]", composed from conf/ like a run of
its own (`algo=<algo>` at this run's scale, its `algo_scale`, seed 0 unless the spec
says otherwise) and sharing this run's character, motion, runtime and evaluation; or
an existing run, `run:<id>` (or the bare 32-digit id), which must have FINISHED.

Every run carries the tag `stage_hash`: a hash of the resolved config that decides its
result, its upstream stages' hashes in place of their specs (so a changed upstream stage
invalidates everything below it), the contents of the character file and of every clip (not
only their paths) and the code's version (`tracking.stage_code`: the package's version, or the
git commit; `orchestrator.provenance`), and nothing that does not change the result (`run_dir`,
`progress`, `tracking`, `preset`, how the runtime is hosted).

Resolving a need looks for a FINISHED run with that hash whose files all landed where the run trusts
(`trusted_sources`): its own experiment and those `tracking.reuse_from` names, never, unless it says
"*", any experiment of a shared store (anyone who can write to it could otherwise plant a run with a
hash that public configs predict). On an authenticated server (`orchestrator.tracking.identity`) its
own experiment counts only if the server gives this user MANAGE on it (its creator has it), and there
only runs recorded as this user's; an experiment `tracking.reuse_from` names is trusted whoever wrote
it, and the line that reuses a run says whose it is. Found, a run is reused, its artifacts downloaded
and checked, and its provenance (run, experiment, user, git commit) recorded as tags on the run that
reuses it; not found (or only FAILED, or unfinished), the stage runs now, in this process, into the
same store (by the `train` function the caller hands in: `orchestrator.build.train_stage`). Every spec of the
whole chain is composed and checked (`plan`) before any stage trains. A sweep resolves its
points' needs once, before the points (`orchestrator.sweep`), so they all find the same stages.

The hash names the method by `algo.name`, never by the module path of its class
(`algo._target_`), so that method modules can move without orphaning stored stages. (Stages
stored before this rule hashed `_target_` too: they are retrained once.)
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from orchestrator import checkpoint
from orchestrator.compose import CONF_DIR, compose, find_method, validate
from orchestrator.provenance import code_version, inputs_digest
from orchestrator.schema import Config, ConfigError
from orchestrator.tracking import identity
from orchestrator.tracking.query import complete_runs, find_finished
from orchestrator.tracking.uri import redact
from orchestrator.upstream import RUN_ID, StageError, Upstream, existing_run, manifest_digest, provenance, short_error

# Trains a stage's config with its resolved upstream stages under its stage hash; returns its run id.
TrainStage = Callable[[Config, dict[str, Upstream], str], str]
# Keys that do not change what a run produces; runtime keeps only what changes the samples.
NOT_RESULT = ("run_dir", "progress", "tracking", "resume", "preset", "sweep_seeds", "scale_name", "stage_overrides")
RUNTIME_RESULT = ("rollout_workers", "envs_per_worker")
# What a run is expected to take, and which replay buffers it keeps on disk: not what it computes.
LOOP_NOT_RESULT = ("expected_minutes", "replay_keep")
# What an upstream stage shares with the run that needs it.
SHARED = (
    "character", "motion", "runtime", "sim", "eval", "tracking", "progress", "preset", "scale_name", "stage_overrides"
)  # fmt: skip
SECTIONS_SHARED = ("character", "motion", "runtime", "sim", "eval", "tracking")
EXPERT_TAG = re.compile(r"^upstream\.(.+\.)?expert(\.\d+)?$")


def config_hash(cfg: Config, upstream: dict[str, str] | None = None) -> str:
    """The hash of what decides `cfg`'s result; `upstream` maps each need's role to its stage hash."""
    d: dict[str, Any] = asdict(cfg)
    for key in NOT_RESULT:
        d.pop(key, None)
    d["runtime"] = {k: d["runtime"][k] for k in RUNTIME_RESULT}
    # The engine changes the physics (MuJoCo Warp computes in float32); its device does not. MuJoCo C is left
    # out, so that stages stored before the switch existed keep their hashes.
    sim = d.pop("sim")
    if sim["backend"] != "mujoco":
        d["sim_backend"] = sim["backend"]
    # `algo` is the method's own config (its sections and its loop: a knob of another method changes no hash here).
    # The method is named by algo.name; its class's module path (_target_) is where code lives, not what it computes.
    d["algo"] = {k: v for k, v in d["algo"].items() if k != "_target_"}
    d["algo"]["loop"] = {k: v for k, v in d["algo"]["loop"].items() if k not in LOOP_NOT_RESULT}
    d["algo"]["needs"] = dict(sorted((upstream or {}).items()))
    d["inputs"] = inputs_digest(cfg.character.xml, cfg.motion.clips)
    d["code"] = code_version(cfg.tracking.stage_code)
    blob = json.dumps(d, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def upstream_config(cfg: Config, spec: str, role: str) -> Config:
    """The config of the stage `spec` ("<algo> [key=value ...]") as `cfg` needs it in `role`; then
    `cfg.stage_overrides[<algo>]`, which apply to that method's stages anywhere above."""
    name, *overrides = spec.split()
    overrides += list(cfg.stage_overrides.get(name, []))
    bad = [o for o in overrides if "=" not in o or o.startswith(("+", "~"))]
    if bad:
        raise ConfigError(f"algo.needs.{role}: {bad[0]!r} is not a key=value override of the {name} stage")
    methods = sorted(p.stem for p in (CONF_DIR / "algo").glob("*.yaml"))
    if name not in methods:
        raise ConfigError(
            f"algo.needs.{role}: cannot compose stage {spec!r}: no method {name!r} ({', '.join(methods)})"
        )
    try:
        base = compose([f"algo={name}", f"scale={cfg.scale_name}"])
    except Exception as e:
        raise ConfigError(f"algo.needs.{role}: cannot compose stage {spec!r} ({short_error(e)})") from None
    shared = {k: OmegaConf.structured(getattr(cfg, k)) if k in SECTIONS_SHARED else getattr(cfg, k) for k in SHARED}
    shared["stage_overrides"] = OmegaConf.create(cfg.stage_overrides)
    OmegaConf.set_struct(base, False)  # the shared stage_overrides and needs may add keys; validate checks them
    try:
        merged = OmegaConf.merge(base, shared, {"run_dir": cfg.run_dir}, OmegaConf.from_dotlist(overrides))
        return validate(merged)
    except Exception as e:
        raise ConfigError(f"algo.needs.{role} ({spec}): {short_error(e)}") from None


def needs_of(cfg: Config) -> dict[str, str]:
    """Role → spec of every stage `cfg` reads: its `algo.needs` as its method expands them (`Method.needs_of`:
    the demos stage's one expert per clip)."""
    return find_method(cfg.algo._target_).needs_of(cfg)


def plan(cfg: Config, seen: tuple[str, ...] = ()) -> None:
    """Compose every stage of `cfg`'s chain (ConfigError naming the first spec that cannot be), before any
    stage is looked up or trained; a spec that comes back to one above it is refused too."""
    for role, spec in needs_of(cfg).items():
        if RUN_ID.fullmatch(spec.strip()):
            continue
        name = spec.split()[0] if spec.split() else spec
        if name in seen:
            raise ConfigError(f"algo.needs.{role}: stage {spec!r} needs itself (through {' -> '.join(seen)})")
        plan(upstream_config(cfg, spec, role), (*seen, cfg.algo.name))


@dataclass(frozen=True)
class Trust:
    """Where a run may reuse stages from: `experiments` ("*": any), of which those in `only` only runs recorded
    as that user's; `note` says why the run's own experiment is left out, when it is."""

    experiments: list[str]
    only: dict[str, str]
    note: str = ""

    def where(self, uri: str) -> str:
        """The experiments, as the line that trains a stage names them."""
        if "*" in self.experiments:
            return f"any experiment of {redact(uri)}"
        named = ", ".join(
            f"{e!r} (runs by {self.only[e]})" if e in self.only else repr(e) for e in dict.fromkeys(self.experiments)
        )
        return f"experiment(s) {named or 'none'} of {redact(uri)}{self.note}"


def trusted_sources(cfg: Config, uri: str, experiment: str) -> Trust:
    """Where this run may reuse stages from: its own experiment and `tracking.reuse_from` ("*": any). On a server
    that authenticates its users, its own experiment only if the server gives this user MANAGE on it, and there only
    the user's own runs (an admin's: any run there); an experiment reuse_from names is trusted whoever made it."""
    named = list(cfg.tracking.reuse_from)
    who = identity.whoami(uri)
    # An admin may write anywhere, as on a store without users (the private server of a parallel sweep, in front of
    # its own SQLite file, is run as its admin).
    if who is None or who.admin or experiment in named or "*" in named:
        return Trust([experiment, *named], {})
    access = identity.experiment_access(uri, who, experiment)
    if access.permission == "MANAGE":
        return Trust([experiment, *named], {experiment: who.user})
    note = (
        f"; not experiment {experiment!r}, which is not {who.user}'s (the server gives them {access.permission} on "
        "it, not MANAGE): name it in tracking.reuse_from to trust its runs"
    )
    return Trust(named, {}, note)


def resolve(cfg: Config, uri: str, workdir: Path, experiment: str, train: TrainStage, log=print) -> dict[str, Upstream]:
    """Every need of `cfg`, reused from the store or trained now by `train` (upstream first); role → Upstream."""
    plan(cfg)
    return _resolve(cfg, uri, workdir, experiment, train, log)


def _resolve(cfg: Config, uri: str, workdir: Path, experiment: str, train: TrainStage, log) -> dict[str, Upstream]:
    return {role: ensure(role, spec, cfg, uri, workdir, experiment, train, log) for role, spec in needs_of(cfg).items()}


def ensure(
    role: str, spec: str, cfg: Config, uri: str, workdir: Path, experiment: str, train: TrainStage, log=print
) -> Upstream:
    cache = workdir / "upstream" / role
    run_id = RUN_ID.fullmatch(spec.strip())
    if run_id:
        given = existing_run(role, run_id.group(1), uri, cache)
        origin = given.provenance
        log(
            f"stage {role}: using run {given.run_id} as algo.needs gives it, of experiment {origin['experiment']!r}, "
            f"user {origin['user']}, commit {origin['git_commit'][:12]}"
        )
        return given
    up = upstream_config(cfg, spec, role)
    above = _resolve(up, uri, workdir, experiment, train, log)
    h = config_hash(up, {r: u.stage_hash for r, u in above.items()})
    lineage = {r: u.run_id for r, u in above.items()}
    for r, u in above.items():
        lineage.update({f"{r}.{k}": v for k, v in u.lineage.items()})
    trust = trusted_sources(cfg, uri, experiment)
    for found, digest in complete_runs(uri, h, trust.experiments, only=trust.only):
        origin = provenance(role, uri, found)
        stage = Upstream(role, up.algo.name, found, h, uri, cache, True, lineage, origin, digest)
        try:
            stage.verify()
        except StageError as e:
            log(f"{e}; not used")
            continue
        named = " (named in tracking.reuse_from)" if origin["experiment"] != experiment else ""
        log(
            f"stage {role}: reusing {up.algo.name} run {found} (hash {h}) of experiment {origin['experiment']!r}"
            f"{named}, user {origin['user']}, commit {origin['git_commit'][:12]}"
        )
        return stage
    up.run_dir = str(workdir / "stages" / f"{up.algo.name}-{h[:8]}")
    # A stage cut short here before (its run FAILED or never ended) continues from its last checkpoint.
    up.resume = checkpoint.latest(Path(up.run_dir) / "checkpoints") is not None
    up.tracking.uri = uri
    up.tracking.experiment = experiment
    up.tracking.run_name = f"{up.algo.name} stage {h[:8]}"
    how = "resuming it from its last checkpoint" if up.resume else "training it"
    log(f"stage {role}: no finished {up.algo.name} run with hash {h} in {trust.where(uri)}; {how} in {up.run_dir}")
    new_id = train(up, above, h)
    origin, digest = provenance(role, uri, new_id), manifest_digest(role, uri, new_id)
    return Upstream(role, up.algo.name, new_id, h, uri, cache, False, lineage, origin, digest)


def pending(cfg: Config, uri: str, experiment: str) -> list[Config]:
    """The stages of `cfg`'s chain that `resolve` would train now: those no FINISHED run with their hash holds in
    a trusted experiment, upstream first, each once."""
    trust, todo, seen = trusted_sources(cfg, uri, experiment), [], set()

    def hashes_above(c: Config) -> dict[str, str]:
        above = {}
        for role, spec in needs_of(c).items():
            given = RUN_ID.fullmatch(spec.strip())
            if given:
                above[role] = given.group(1)
                continue
            up = upstream_config(c, spec, role)
            above[role] = h = config_hash(up, hashes_above(up))
            if h not in seen and not find_finished(uri, h, trust.experiments, trust.only):
                todo.append(up)
            seen.add(h)
        return above

    hashes_above(cfg)
    return todo


def expected_time(cfg: Config, uri: str, experiment: str, points: int = 1, jobs: int = 1) -> str:
    """One line: the minutes a run (or sweep) of `cfg` is expected to take on a 2-core machine, from each method's
    measured `algo.loop.expected_minutes`: the stages it has to train, one at a time, then `points` runs of `cfg`,
    `jobs` at a time."""
    todo = pending(cfg, uri, experiment)
    counts: dict[str, list[float]] = {}
    for up in todo:
        counts.setdefault(up.algo.name, []).append(up.algo.loop.expected_minutes)
    rounds = -(-points // max(jobs, 1))
    parts = [f"{len(m)} {name} stage{'s' * (len(m) > 1)} {sum(m):.0f} min" for name, m in counts.items()]
    point = cfg.algo.loop.expected_minutes
    parts.append(f"{points} run{'s' * (points > 1)} of {cfg.algo.name}, {jobs} at a time, {rounds * point:.0f} min")
    unknown = [n for n, m in counts.items() if not all(m)] + ([cfg.algo.name] if not point else [])
    total = sum(sum(m) for m in counts.values()) + rounds * point
    said = f"expected time on a 2-core machine: about {total:.0f} min ({'; '.join(parts)})"
    if unknown:
        said += f"; not measured at scale {cfg.scale_name}: {', '.join(dict.fromkeys(unknown))}"
    return said


def lineage_tags(upstream: dict[str, Upstream]) -> dict[str, str]:
    """Tags that say which stages a run used: upstream.<role>[.<role>...] = run id, where each stage it used
    directly came from (upstream.<role>.experiment, .user, .git_commit), and expert_run_id."""
    tags: dict[str, str] = {}
    for role, u in upstream.items():
        tags[f"upstream.{role}"] = u.run_id
        tags[f"upstream.{role}.reused"] = str(u.reused).lower()
        tags.update({f"upstream.{role}.{k}": v for k, v in u.provenance.items()})
        tags.update({f"upstream.{role}.{k}": v for k, v in u.lineage.items()})
    experts = [v for k, v in tags.items() if EXPERT_TAG.search(k)]
    if experts:  # one expert, or one per clip (`upstream.demos.expert.0`, ...)
        tags["expert_run_id"] = ",".join(dict.fromkeys(experts))
    return tags
