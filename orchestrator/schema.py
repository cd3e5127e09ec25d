"""The configuration schema: one dataclass per config group, each field documented where it is declared.

`conf/` YAML is type-checked against these when Hydra composes it (`orchestrator.compose` registers
`Config` in Hydra's ConfigStore and validates), and each dataclass's `__post_init__` refuses a bad
value with its key named, before any process starts. `algo` is a method's own config, declared beside
the method (a `MethodConfig` with the method's sections: the learners' configs, `WorldModelConfig`,
`VAEConfig`, ..., used as they are, so that a field is documented once, where it is declared). This
module holds only the dataclasses (and `ConfigError`); it reads no method's code.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, fields

from omegaconf import MISSING

from orchestrator.errors import ConfigError
from orchestrator.provenance import CODE_VERSIONS
from orchestrator.tracking.uri import tracking_uri_error
from workers.body.character import file_problem
from workers.learners.base import COMPILE_MODES as LEARNER_COMPILE
from workers.learners.base import DEVICES as LEARNER_DEVICES
from workers.motion.errors import ClipError
from workers.motion.formats import resolve
from workers.sim.terrain import TerrainConfig
from workers.sim.warp_physics import INSTALL_HINT, warp_available

__all__ = ["ConfigError"]

SIM_BACKENDS = ("mujoco", "warp")
PIN_MODES = ("auto", "shared")  # runtime.pin_cores (orchestrator/runtime/cores.py); not "off": YAML reads it as false

LOCOMOTION = [
    "humanoid3d_walk",
    "humanoid3d_run",
    "walker/turn_left0",
    "walker/turn_left1",
    "walker/turn_right0",
    "walker/turn_right1",
]


# The largest seed a run takes: an unsigned 32-bit one. NumPy's SeedSequence refuses a negative seed, torch's
# manual_seed one above 2**64 - 1, and a run seeds its components with seed * 1000 + offset (orchestrator.world).
SEED_MAX = 2**32 - 1


@dataclass
class CharacterConfig:
    # MJCF file of the character; null uses the bundled humanoid.
    xml: str | None = None
    # Physics and control rates (PhysicsVAE: 480 / 30 Hz; see the README for the measurement).
    sim_hz: float = 480.0
    control_hz: float = 30.0
    # Collisions between the character's own bodies.
    self_collision: bool = False

    def __post_init__(self) -> None:
        if self.xml is not None and (problem := file_problem(self.xml)):
            raise ConfigError(f"character.xml: {self.xml}: {problem}")
        ratio = self.sim_hz / self.control_hz if self.control_hz > 0 else 0
        if self.control_hz <= 0 or ratio < 1 or abs(ratio - round(ratio)) > 1e-6:
            raise ConfigError(f"character.sim_hz ({self.sim_hz}) must be a whole multiple of control_hz")


@dataclass
class MotionConfig:
    # Bundled clip names (`python -m orchestrator.clips list`) or paths to DeepMimic, BVH or NPZ files.
    clips: list[str] = field(default_factory=lambda: list(LOCOMOTION))
    # Add left-right mirrored copies (ControlVAE doubles its data this way).
    mirror: bool = True
    # Processed-clip cache; null: ~/.cache/mocap-orchestrator/motion or $MOCAP_CACHE_DIR.
    cache_dir: str | None = None
    # BVH import: source joint name -> our body name, added to (and overriding) the default map.
    joint_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.clips:
            raise ConfigError("motion.clips is empty")
        for i, clip in enumerate(self.clips):
            try:
                resolve(clip)
            except ClipError as e:
                raise ConfigError(f"motion.clips[{i}]: {e}") from None


@dataclass
class LoopConfig:
    """The loop knobs every method has; a method's config names the loop it runs (`ReplayLoop`, `PPOLoop`, or one
    of its own beside its module, such as ControlVAE's)."""

    # Training iterations; each collects, updates the learners, publishes weights and reports.
    iterations: int = 200
    # Control steps each rollout worker collects per iteration, over all its environments.
    collect_steps: int = 16
    # A worker more than this many versions behind the newest weights refreshes before collecting.
    staleness: int = 1
    # Iterations between checkpoints (and at the end); 0: only at the end.
    checkpoint_every: int = 50
    # Checkpoints kept, the newest, in run_dir/checkpoints (older ones are deleted after each save; a resume falls
    # back to an older one when the newest does not load). At least 1. The store keeps tracking.store_checkpoints.
    checkpoint_keep: int = 3
    # Of those, how many newest keep their replay buffers beside them in run_dir/checkpoints (`replay-N.pt`, never
    # uploaded; ControlVAE's default 50,000 transitions are 87 MB); 0: none saved (a resume refills them).
    replay_keep: int = 1
    # Iterations between evaluations (and at the end); 0: only at the end.
    eval_every: int = 0
    # The wall minutes one run of this method takes at this scale, measured on a 2-core machine (this project's
    # CI machine; conf/algo_scale/*_cpu.yaml says when); 0: not measured. A sweep adds up the stages it has to
    # train and its points and prints the expected time before it starts (orchestrator.stages.expected_time).
    expected_minutes: float = 0.0
    # A budget in wall time as well: the run ends (evaluated and checkpointed as at its last
    # iteration) once this many minutes have passed, if `iterations` have not ended it first; 0: none.
    max_minutes: float = 0.0
    # Collection episodes end on a fall (a body other than the feet touching the ground) when true;
    # ControlVAE only ends them on a tracking failure (head 0.5 m off for 1 s) or at a length cap.
    end_on_fall: bool = True
    # Cap on a collection episode's control steps (ControlVAE 512); 0: none.
    max_episode_steps: int = 512

    def __post_init__(self) -> None:
        if self.max_episode_steps < 0:
            raise ConfigError(f"algo.loop.max_episode_steps must be non-negative, got {self.max_episode_steps}")
        if self.replay_keep < 0:
            raise ConfigError(f"algo.loop.replay_keep must be non-negative, got {self.replay_keep}")
        for key in ("iterations", "collect_steps", "checkpoint_keep"):
            if getattr(self, key) < 1:
                raise ConfigError(f"algo.loop.{key} must be at least 1, got {getattr(self, key)}")


@dataclass
class ReplayLoop(LoopConfig):
    """The loop of a method whose learners sample a replay of its collections (ControlVAE, PULSE, the task)."""

    # Learner samples (transitions in rollouts) per collected sample, for each learner.
    replay_ratio: float = 4.0
    # Transitions kept in the replay buffer (ControlVAE N_B = 50,000); the oldest are evicted.
    replay_capacity: int = 50_000
    # Transitions collected before the first update.
    warmup: int = 1_000
    # Probability of z from the prior instead of the posterior while collecting (ControlVAE: 0.4).
    prior_probability: float = 0.4

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.replay_capacity < 1:
            raise ConfigError(f"algo.loop.replay_capacity must be at least 1, got {self.replay_capacity}")
        if self.replay_ratio <= 0:
            raise ConfigError(f"algo.loop.replay_ratio must be positive, got {self.replay_ratio}")
        if not 0 <= self.prior_probability <= 1:
            raise ConfigError(f"algo.loop.prior_probability must be in [0, 1], got {self.prior_probability}")


@dataclass
class PPOLoop(LoopConfig):
    """The loop of a method trained by PPO (AMP, the tracking expert, the task's PPO trainer)."""

    # Collect the next batch while the learners train on this one (on Ray the workers then never wait for an
    # update). Each batch is one iteration older than the policy it trains, which PPO's clipped importance ratio
    # tolerates (asynchronous PPO variants do the same); false keeps PPO strictly on-policy.
    overlap: bool = False


@dataclass
class MethodConfig:
    """`algo`: what every method's config has. Each method declares its own beside its module (a subclass with
    its sections and its loop: `orchestrator.algos.controlvae.ControlVAEAlgo`, ...), the schema that
    conf/algo/<name>.yaml names in its defaults list and `orchestrator.compose.validate` checks it against."""

    # The method's class (orchestrator/algos/): conf/algo/<name>.yaml sets it.
    _target_: str = MISSING
    # The method's name: the MLflow tags `algo` and `stage`.
    name: str = MISSING
    loop: LoopConfig = field(default_factory=LoopConfig)
    # The stages this method needs, role -> spec: "<algo> [key=value ...]" (a stage composed like a
    # run of its own and reused when an identical one has finished in the store) or "run:<id>"
    # (orchestrator/stages.py). The method's class says which roles it needs.
    needs: dict[str, str] = field(default_factory=dict)


def sections_of(config: type) -> tuple[str, ...]:
    """The sections of a method's config class: its fields beyond those every method has."""
    common = {f.name for f in fields(MethodConfig)}
    return tuple(f.name for f in fields(config) if f.name not in common)


PLACEMENTS = ("PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD")


@dataclass
class RuntimeConfig:
    # The backend's class: orchestrator.runtime.local.LocalRuntime or orchestrator.runtime.ray.RayRuntime.
    _target_: str = "orchestrator.runtime.local.LocalRuntime"
    # Rollout workers and the environments each steps as one batch.
    rollout_workers: int = 2
    envs_per_worker: int = 16
    # Ray only: cluster address (null starts a local Ray for the run; "auto" or "ray://host:port" joins one).
    address: str | None = None
    # Ray only: seconds to wait for `address` to answer before giving up with one line naming it.
    connect_timeout_s: float = 20.0
    # Ray only: how the components' placement group is laid out over the nodes: PACK (as few nodes
    # as fit), SPREAD (over as many as possible), STRICT_PACK or STRICT_SPREAD.
    placement: str = "PACK"
    # Ray only: CPUs per rollout worker and per learner, GPUs per learner, actor restarts after a crash.
    worker_cpus: float = 1.0
    learner_cpus: float = 1.0
    learner_gpus: float = 0.0
    # Ray only: GPUs per rollout worker (a fraction shares one), for sim.backend=warp on sim.device=cuda; 0 with
    # a Ray started for the run: an equal share of the first GPU with the learners that take one.
    worker_gpus: float = 0.0
    max_restarts: int = 3
    # Ray only: object store size (MiB) when Ray is started for the run.
    object_store_mb: int = 512
    # Torch threads in each process (1 avoids contention between actors sharing cores).
    torch_threads: int = 1
    # Threads that step each rollout worker's environments (mujoco.batch's pool). More than one pays
    # when cores are free (one worker, or more cores than actors): `bench rollout --threads 2` measured
    # one worker of 32 environments at 1.15-1.27x raw single-core mj_step on 2 cores, 0.62-0.74x with 1.
    sim_threads: int = 1
    # Where the learners compute: cpu | cuda (the first GPU the learner's process sees: under Ray, the one
    # runtime.learner_gpus reserved for its actor; locally, the machine's first) | auto (cuda whenever the
    # learner's process sees a GPU, else cpu). Weights reach the rollout workers as CPU tensors either way.
    learner_device: str = "auto"
    # The learners' losses through torch.compile: eager | default | reduce-overhead (CUDA graphs, for a GPU).
    # The first update of each compiles (minutes on a laptop's cores, cached on disk for the next run; see
    # docs/learners.md); the AMP discriminator's gradient penalty stays eager.
    learner_compile: str = "eager"
    # Ray started for the run only: auto gives each component the loop waits on (a method's
    # `Component.own_core`, e.g. ControlVAE's VAE learner) a CPU core of its own and every other actor the
    # cores left, when there are more cores than such components (Linux); shared leaves it to the scheduler.
    pin_cores: str = "auto"

    def __post_init__(self) -> None:
        if self.learner_device not in LEARNER_DEVICES:
            raise ConfigError(f"runtime.learner_device must be one of {LEARNER_DEVICES}, got {self.learner_device!r}")
        if self.pin_cores not in PIN_MODES:
            raise ConfigError(f"runtime.pin_cores must be one of {PIN_MODES}, got {self.pin_cores!r}")
        if self.learner_compile not in LEARNER_COMPILE:
            raise ConfigError(f"runtime.learner_compile must be one of {LEARNER_COMPILE}, got {self.learner_compile!r}")
        if self.learner_gpus < 0:
            raise ConfigError(f"runtime.learner_gpus must be non-negative, got {self.learner_gpus}")
        if self.worker_gpus < 0:
            raise ConfigError(f"runtime.worker_gpus must be non-negative, got {self.worker_gpus}")
        if self.rollout_workers < 1:
            raise ConfigError(f"runtime.rollout_workers must be at least 1, got {self.rollout_workers}")
        if self.envs_per_worker < 1:
            raise ConfigError(f"runtime.envs_per_worker must be at least 1, got {self.envs_per_worker}")
        if self.sim_threads < 1:
            raise ConfigError(f"runtime.sim_threads must be at least 1, got {self.sim_threads}")
        if self.placement not in PLACEMENTS:
            raise ConfigError(f"runtime.placement must be one of {PLACEMENTS}, got {self.placement!r}")


@dataclass
class TrackingConfig:
    # Off: nothing is written (a no-op tracker).
    enabled: bool = True
    # MLflow tracking URI; null: an embedded SQLite store in the run directory.
    uri: str | None = None
    # MLflow experiment; null: the preset's name.
    experiment: str | None = None
    # Run name; null: made from the overrides.
    run_name: str | None = None
    # Log the trained policy as an MLflow model at the end of the run (mlflow.pytorch.log_model).
    log_model: bool = True
    # Seconds between system metrics (CPU, memory, disk, network: MLflow's system/ metrics); 0: none.
    system_metrics_s: float = 10.0
    # Upstream stages are reused from FINISHED runs of this run's own experiment and of the experiments named
    # here; "*" trusts every experiment of the store (anyone who can write to it could plant a stage).
    reuse_from: list[str] = field(default_factory=list)
    # What of the code a stage hash covers: "source" (a digest of the source files that compute stages,
    # orchestrator.provenance.SOURCE: an edit there retrains, elsewhere not), "version" (the package's; commits
    # between versions reuse stages) or "commit" (the git commit: every commit retrains every stage).
    stage_code: str = "source"
    # Seconds an artifact upload (a checkpoint, a video) may wait on the store per request; other requests get 3 s.
    artifact_timeout_s: int = 60
    # Uploads in a row that time out before the run stops trying: the files wait in the run directory's
    # tracking spool for orchestrator.tracking.mlflow.replay_spool, and the run ends without them.
    artifact_tries: int = 3
    # The newest checkpoints kept in the MLflow run's artifacts (networks, optimizers and counters: what a stage's
    # consumers read; never the replay buffers), at least 1; run_dir keeps algo.loop.checkpoint_keep of them.
    store_checkpoints: int = 1

    def __post_init__(self) -> None:
        if self.store_checkpoints < 1:
            raise ConfigError(f"tracking.store_checkpoints must be at least 1, got {self.store_checkpoints}")
        if self.uri is not None and (problem := tracking_uri_error(self.uri)):
            raise ConfigError(f"tracking.uri: {problem}")
        if self.stage_code not in CODE_VERSIONS:
            raise ConfigError(f"tracking.stage_code must be one of {', '.join(CODE_VERSIONS)}, got {self.stage_code!r}")
        for i, name in enumerate(self.reuse_from):
            if not str(name).strip():
                raise ConfigError(f"tracking.reuse_from[{i}] is empty (an experiment's name, or '*')")
        if self.artifact_timeout_s < 1 or self.artifact_tries < 1:
            raise ConfigError(
                f"tracking.artifact_timeout_s and tracking.artifact_tries must be at least 1, "
                f"got {self.artifact_timeout_s} and {self.artifact_tries}"
            )


@dataclass
class EvalConfig:
    # Time-until-fall (PhysicsVAE Fig. 9): rollouts from one fixed start, the walk clip's frame 0 (mid-stride,
    # not a standing pose: the paper does not say its start), z from the prior every step.
    fall_rollouts: int = 100
    fall_max_seconds: float = 60.0
    # Tracking error (ControlVAE Fig. 14): every clip cut into consecutive segments of this many
    # seconds, each tracked with the posterior from its first frame.
    tracking_seconds: float = 2.0
    # Random sampling (ControlVAE Fig. 5): rollouts from random dataset states, z from the prior for
    # random_seconds of simulated time (ControlVAE: 200 steps at its 20 Hz = 10 s; 300 steps at our 30 Hz).
    random_rollouts: int = 32
    random_seconds: float = 10.0
    # Pose error after dynamic time warping (AMP Eq. 10, Table 3): episodes of up to pose_seconds
    # from random reference starts, deterministic actions (AMP: 32 episodes of up to 20 s per seed).
    pose_episodes: int = 32
    pose_seconds: float = 20.0
    # Downstream tasks: episodes of task_seconds under the task policy's mean, one per goal of a fixed
    # set (the same goals for every run: seeded by task_goal_seed, not by the run's seed).
    task_goals: int = 16
    task_seconds: float = 10.0
    task_goal_seed: int = 1234
    # Evaluate the untrained policy before the first iteration: the first point of the eval/ curves,
    # and the baseline of the closing summary.
    at_start: bool = True
    # Videos (MP4, MuJoCo's offscreen renderer; MUJOCO_GL=egl or osmesa) logged at each evaluation:
    # video_rollouts time-until-fall rollouts and one tracked clip beside its reference (a ghost),
    # each of up to video_seconds, video_width x video_height pixels.
    video: bool = True
    video_rollouts: int = 2
    video_seconds: float = 6.0
    video_width: int = 480
    video_height: int = 320

    def __post_init__(self) -> None:
        if self.video_rollouts < 0 or self.video_seconds <= 0 or min(self.video_width, self.video_height) < 16:
            raise ConfigError("eval.video_rollouts must be >= 0, eval.video_seconds positive, video size >= 16 px")
        for key in ("fall_rollouts", "random_rollouts"):
            if getattr(self, key) < 1:
                raise ConfigError(f"eval.{key} must be at least 1, got {getattr(self, key)}")
        if self.task_goals < 1 or self.task_seconds <= 0:
            raise ConfigError("eval.task_goals must be at least 1 and eval.task_seconds positive")
        if self.pose_episodes < 1 or self.pose_seconds <= 0:
            raise ConfigError("eval.pose_episodes must be at least 1 and eval.pose_seconds positive")
        if self.fall_max_seconds <= 0 or self.tracking_seconds <= 0 or self.random_seconds <= 0:
            raise ConfigError("eval.fall_max_seconds, eval.tracking_seconds and eval.random_seconds must be positive")


@dataclass
class SimSettings:
    # The physics engine of the rollout workers and evaluations: mujoco (MuJoCo C on CPU cores) or warp
    # (MuJoCo Warp: the `warp` extra; docs/warp.md). A method runs unchanged on either.
    backend: str = "mujoco"
    # warp only: the Warp device, cpu (correctness, slow) | cuda | cuda:N.
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.backend not in SIM_BACKENDS:
            raise ConfigError(f"sim.backend must be one of {SIM_BACKENDS}, got {self.backend!r}")
        if self.device != "cpu" and not re.fullmatch(r"cuda(:\d+)?", self.device):
            raise ConfigError(f"sim.device must be cpu, cuda or cuda:N, got {self.device!r}")
        if self.backend == "warp" and not warp_available():
            raise ConfigError(
                f"sim.backend: warp needs mujoco-warp and warp-lang, which are not installed ({INSTALL_HINT})"
            )


@dataclass
class Config:
    character: CharacterConfig = field(default_factory=CharacterConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    algo: MethodConfig = field(default_factory=MethodConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    # The ground the rollout workers and evaluations simulate (not shared with upstream stages: a task on
    # rough terrain uses a skill model trained on flat ground).
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    # The simulator's engine and device.
    sim: SimSettings = field(default_factory=SimSettings)
    # Seed of everything: network initialisation, sampling, the simulators.
    seed: int = 0
    # The preset that made this config (the MLflow experiment unless tracking.experiment says otherwise).
    preset: str = "default"
    # Where checkpoints, the embedded MLflow store and spooled metrics go.
    run_dir: str = "outputs/run"
    # Continue the run in run_dir from its last checkpoint (same MLflow run).
    resume: bool = False
    # Show a progress bar.
    progress: bool = True
    # The seeds a sweep preset runs at this scale, as a Hydra sweep ("0,1,2"; scale/ sets it).
    sweep_seeds: str = "0,1,2"
    # The scale this config was composed at (scale/ sets it); upstream stages are composed at the same.
    scale_name: str = "laptop"
    # Overrides for upstream stages wherever they occur in the chain, by method: e.g.
    # '+stage_overrides.tracker=["algo.loop.iterations=600"]' trains a longer expert for every stage above
    # this run, '+stage_overrides.demos=["algo.needs.expert=run:<id>"]' uses a given expert run.
    stage_overrides: dict[str, list[str]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0 <= self.seed <= SEED_MAX:
            raise ConfigError(
                f"seed: {self.seed} is outside 0 ... {SEED_MAX} (an unsigned 32-bit seed, which every generator takes)"
            )
        if self.sim.backend == "warp" and self.terrain.kind != "flat":
            raise ConfigError(
                f"terrain.kind: {self.terrain.kind} terrain is a height field, which sim.backend=warp cannot simulate "
                "yet (MuJoCo Warp: at most 4 contacts per height-field collider; docs/warp.md); use sim.backend=mujoco"
            )
