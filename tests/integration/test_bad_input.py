"""Bad input at run time, tried as a new user would: one line on stderr naming the file, key or address,
exit status 2, no traceback, and nothing already saved touched (no run directory made, no checkpoint or
run.json rewritten, no MLflow run reopened, no MUJOCO_LOG.TXT in the working directory).

Most cases call the entry point in this process (`main` as `python -m orchestrator` calls it, after
Hydra's composition); one runs the real command, and the checkpoint cases resume a real smoke run.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import open_dict

from orchestrator import preflight
from orchestrator.__main__ import main
from orchestrator.clips import main as motion_main
from orchestrator.compose import register, validate
from orchestrator.schema import ConfigError

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
WALK = Path(pybullet_data.getDataPath()) / "data" / "motions" / "humanoid3d_walk.txt"
register()


def compose_smoke(run_dir: Path, cache: Path, *overrides: str):
    common = ["runtime=local", "scale=smoke", "progress=false", f"run_dir={run_dir}", f"motion.cache_dir={cache}"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=[*common, *overrides], return_hydra_config=True)


def run_main(tmp_path: Path, capsys, *overrides: str, run_dir: Path | None = None) -> tuple[int, str]:
    """`python -m orchestrator runtime=local scale=smoke progress=false ... <overrides>` in this process, in
    tmp_path as the working directory: (exit status, stderr)."""
    cfg = compose_smoke(run_dir or tmp_path / "run", tmp_path / "cache", *overrides)
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]
    capsys.readouterr()
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        with pytest.raises(SystemExit) as exit_:
            main.__wrapped__(cfg)
    finally:
        os.chdir(cwd)
        HydraConfig.instance().cfg = None  # as outside a Hydra app, for the tests that follow
    return exit_.value.code, capsys.readouterr().err


def assert_refused(tmp_path: Path, code: int, err: str, *names: str) -> str:
    """Exit status 2, one line on stderr naming each of `names`, no traceback, no MuJoCo log."""
    lines = err.strip().splitlines()
    assert code == 2, err
    assert "Traceback" not in err
    assert len(lines) == 1, err
    for name in names:
        assert name in lines[-1], lines[-1]
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    return lines[-1]


def walk_frames() -> dict:
    return json.loads(WALK.read_text())


def write_clip(path: Path, doc: dict) -> Path:
    path.write_text(json.dumps(doc))
    return path


# a. A clip that exists but is malformed, in each format ---------------------------------------------
def test_malformed_deepmimic_clip_fails_the_command_before_anything_starts(tmp_path):
    doc = walk_frames()
    doc["Frames"][12] = doc["Frames"][12][:40]
    bad = write_clip(tmp_path / "walk_bad.txt", doc)
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator", "runtime=local", "scale=smoke", "progress=false",
         f"motion.clips=[{bad}]", f"run_dir={run_dir}", f"hydra.run.dir={tmp_path / 'hydra'}",
         f"motion.cache_dir={tmp_path / 'cache'}"],
        cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    line = assert_refused(tmp_path, proc.returncode, proc.stderr, "walk_bad.txt", "frame 12")
    assert line == f"error: clip {bad}: frame 12: expected 44 numbers, got 40"
    assert not run_dir.exists()  # no MLflow store, no run.json: nothing started


def _bad_npz(path: Path) -> None:
    np.savez(path, qpos=np.zeros((10, 40)), fps=30.0)  # our character has 43 coordinates


def _bad_bvh(path: Path) -> None:
    path.write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Xposition Yposition Zposition\n}\n")


MALFORMED = [
    ("walk.json", lambda p: p.write_text('{"Loop": "wrap", "Frames": [[0.03, 1'), "not valid JSON"),
    ("walk.npz", _bad_npz, "expected 43 coordinates a frame, got 40"),
    ("walk_truncated.npz", lambda p: p.write_bytes(b"PK\x03\x04 truncated"), "not a readable .npz"),
    ("walk.bvh", _bad_bvh, "no MOTION section"),
]


@pytest.mark.parametrize("name,write,message", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_clip_in_each_format_is_refused_by_the_checker_and_the_run(tmp_path, capsys, name, write, message):
    bad = tmp_path / name
    write(bad)
    assert motion_main(["check", str(bad)]) == 1
    checked = capsys.readouterr().err.strip()
    assert checked.startswith(f"error: {bad}") and message in checked
    code, err = run_main(tmp_path, capsys, f"motion.clips=[{bad}]")
    line = assert_refused(tmp_path, code, err, str(bad), message)
    assert line == f"error: clip {checked.removeprefix('error: ')}"  # the checker's words
    assert not (tmp_path / "run").exists()


# b. A directory given as a clip ------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["clips", "walk.txt"])
def test_directory_as_a_clip(tmp_path, capsys, name):
    folder = tmp_path / name
    folder.mkdir()
    code, err = run_main(tmp_path, capsys, f"motion.clips=[humanoid3d_walk,{folder}]")
    line = assert_refused(tmp_path, code, err, "motion.clips[1]", str(folder))
    assert line.endswith("is a directory, not a clip file (.txt/.json, .bvh or .npz)")
    assert motion_main(["check", str(folder)]) == 1
    assert "is a directory" in capsys.readouterr().err


# c. A character file that is missing, or is not our skeleton -------------------------------------------
PENDULUM = """<mujoco model="pendulum">
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="pole" pos="0 0 1">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge"/></actuator>
</mujoco>
"""


def test_character_file_missing_or_not_our_skeleton(tmp_path, capsys):
    missing = tmp_path / "humanoid_v2.xml"
    code, err = run_main(tmp_path, capsys, "motion=walk", f"character.xml={missing}")
    line = assert_refused(tmp_path, code, err, "character.xml", str(missing))
    assert line == f"config error: character.xml: {missing}: no such file"

    pendulum = tmp_path / "pendulum.xml"
    pendulum.write_text(PENDULUM)
    code, err = run_main(tmp_path, capsys, "motion=walk", f"character.xml={pendulum}")
    line = assert_refused(tmp_path, code, err, f"character.xml={pendulum}", "not the humanoid skeleton")
    assert "no body root, chest, neck, right_shoulder and 11 more" in line

    # Our humanoid with a knee that is a ball joint: the type is checked, not only the names.
    ball_knee = tmp_path / "ball_knee.xml"
    xml = (ROOT / "workers/body/assets/humanoid.xml").read_text()
    knee = 'name="right_knee" type="hinge" axis="0 -1 0" range="-3.14 0.3"'
    assert knee in xml
    ball_knee.write_text(xml.replace(knee, 'name="right_knee" type="ball" range="0 1"'))
    code, err = run_main(tmp_path, capsys, "motion=walk", f"character.xml={ball_knee}")
    assert "joint right_knee is ball, not hinge" in assert_refused(tmp_path, code, err, str(ball_knee))
    assert not (tmp_path / "run").exists()


# d. A tracking URI with a scheme MLflow does not know ---------------------------------------------------
def test_unknown_tracking_scheme_is_refused_at_composition_and_at_run_time(tmp_path, capsys):
    code, err = run_main(tmp_path, capsys, "motion=walk", "tracking.uri=foo://x")
    line = assert_refused(tmp_path, code, err, "tracking.uri", "'foo'", "foo://x")
    assert line.startswith("config error: tracking.uri: MLflow has no tracking store for the scheme 'foo'")
    assert not (tmp_path / "run").exists()
    # At run time: a URI set after composition (a sweep point takes its parent's) is checked again.
    cfg = validate(_plain(compose_smoke(tmp_path / "run", tmp_path / "cache", "motion=walk")))
    cfg.tracking.uri = "s3://bucket/mlruns"
    with pytest.raises(ConfigError, match=r"^tracking.uri: MLflow has no tracking store for the scheme 's3'"):
        preflight.check(cfg)
    for uri in ("http://127.0.0.1:5000", "sqlite:///x.db", "postgresql+psycopg2://u@h/db"):
        cfg.tracking.uri = uri
        preflight.check(cfg)  # known schemes pass


def test_file_store_is_refused_without_mlflows_opt_in(tmp_path, capsys, monkeypatch):
    # MLflow 3 raises deep in MlflowClient() for a file store unless MLFLOW_ALLOW_FILE_STORE=true.
    monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE", raising=False)
    uri = (tmp_path / "mlruns").as_uri()
    code, err = run_main(tmp_path, capsys, "motion=walk", f"tracking.uri={uri}")
    line = assert_refused(tmp_path, code, err, "tracking.uri", uri, "MLFLOW_ALLOW_FILE_STORE=true")
    assert "sqlite:///" in line and not (tmp_path / "mlruns").exists()
    cfg = validate(_plain(compose_smoke(tmp_path / "run", tmp_path / "cache", "motion=walk")))
    for store in (uri, str(tmp_path / "mlruns")):  # file: and a bare path alike
        cfg.tracking.uri = store
        with pytest.raises(ConfigError, match="MLFLOW_ALLOW_FILE_STORE=true"):
            preflight.check(cfg)
        monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
        preflight.check(cfg)  # with the opt-in, as MLflow itself
        monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE")


def _plain(cfg):
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


# e. A Ray address where nothing answers --------------------------------------------------------------
def test_ray_address_where_nothing_answers_fails_at_once(tmp_path, capsys):
    import time

    start = time.monotonic()
    code, err = run_main(tmp_path, capsys, "motion=walk", "runtime=ray", "runtime.address=127.0.0.1:1")
    line = assert_refused(tmp_path, code, err, "runtime.address=127.0.0.1:1")
    where = "runtime.address=127.0.0.1:1: no Ray cluster at 127.0.0.1:1 (connection refused)"
    assert line == f"error: {where}; is it up (`ray status`)?"
    assert time.monotonic() - start < 60  # not ray.init's minutes of retries
    assert not (tmp_path / "run").exists()


# g. A clip whose values are finite but absurd --------------------------------------------------------
def _far_root(doc):
    for frame in doc["Frames"]:
        frame[1] = 1e30  # x of the root, y-up
    return doc


def _teleport(doc):
    doc["Frames"][12][3] += 5.0  # 5 m sideways in one frame of 1/30 s: 150 m/s
    return doc


def _knee_jump(doc):
    doc["Frames"][12][20] += 2.0  # the right knee (column 20) turns 2 rad in 1/30 s: 60 rad/s
    return doc


ABSURD = [
    ("root_1e30_m", _far_root, "frame 0: root is 1e+30 m from the origin (more than 1000 m)"),
    ("root_150_m_s", _teleport, "frame 12: root moves at 150 m/s from frame 11 (more than 30 m/s)"),
    ("knee_60_rad_s", _knee_jump, "frame 12: right_knee turns at 60.2 rad/s from frame 11 (more than 50 rad/s)"),
]


@pytest.mark.parametrize("name,edit,message", ABSURD, ids=[a[0] for a in ABSURD])
def test_absurd_clip_is_refused_by_the_checker_and_the_run_with_the_frame(tmp_path, capsys, name, edit, message):
    bad = write_clip(tmp_path / f"{name}.txt", edit(walk_frames()))
    assert motion_main(["check", str(bad)]) == 1
    assert capsys.readouterr().err.strip() == f"error: {bad}: {message}"
    code, err = run_main(tmp_path, capsys, f"motion.clips=[{bad}]")
    assert assert_refused(tmp_path, code, err) == f"error: clip {bad}: {message}"
    assert not (tmp_path / "run").exists()


# f. A checkpoint that is truncated, not a weights file, or for other network sizes -------------------
@pytest.fixture(scope="module")
def prior_run(tmp_path_factory) -> Path:
    """A finished smoke run: its run directory with a checkpoint, run.json and the MLflow store."""
    from orchestrator.build import run

    root = tmp_path_factory.mktemp("prior")
    overrides = ("motion=walk", "algo.loop.iterations=1", "eval.video=false", "tracking.log_model=false")
    run(validate(_plain(compose_smoke(root / "run", root / "cache", *overrides))))
    return root / "run"


def _digest(run_dir: Path) -> dict[str, str]:
    return {
        str(p.relative_to(run_dir)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file()
    }


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _zero_tensors(path: Path) -> None:
    """Every tensor zeroed, in an archive that is still valid: only the digest beside it tells."""
    import torch

    state = torch.load(path, weights_only=True)

    def zero(x):
        if isinstance(x, torch.Tensor):
            return torch.zeros_like(x)
        if isinstance(x, dict):
            return {k: zero(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return type(x)(zero(v) for v in x)
        return x

    torch.save(zero(state), path)


def _not_weights(path: Path) -> None:
    path.write_text("step,reward\n1,0.5\n")  # a CSV saved under the checkpoint's name


CHECKPOINTS = [
    ("truncated", _truncate, (), "truncated or corrupt (an incomplete zip archive of"),
    ("not_weights", _not_weights, (), "not a PyTorch weights file"),
    ("zeroed", _zero_tensors, (), "corrupt: its contents do not match the SHA-256 in ckpt-0000001.pt.sha256"),
    (
        "other_sizes",
        lambda path: None,
        ("algo.world_model.hidden=[64,64]",),
        "world_model: size mismatch for net.0.weight: [128, 271] in the checkpoint, [64, 271] in this config's network",
    ),
]


@pytest.mark.slow
@pytest.mark.parametrize("name,spoil,overrides,message", CHECKPOINTS, ids=[c[0] for c in CHECKPOINTS])
def test_unusable_checkpoint_is_named_and_nothing_saved_is_touched(
    tmp_path, capsys, prior_run, name, spoil, overrides, message
):
    from mlflow.tracking import MlflowClient

    run_dir = tmp_path / "run"
    shutil.copytree(prior_run, run_dir)
    ckpt = max((run_dir / "checkpoints").glob("ckpt-*.pt"))
    spoil(ckpt)
    before = _digest(run_dir)
    code, err = run_main(tmp_path, capsys, "motion=walk", "resume=true", *overrides, run_dir=run_dir)
    line = assert_refused(tmp_path, code, err, str(ckpt), message)
    assert line.startswith(f"error: checkpoint {ckpt}: ") and line.endswith("(resume=true; the file is left as it is)")
    assert _digest(run_dir) == before  # checkpoint, run.json and the MLflow store: the same bytes
    client = MlflowClient(f"sqlite:///{run_dir}/mlflow.db")
    run_id = json.loads((run_dir / "run.json").read_text())["run_id"]
    runs = client.search_runs([client.get_run(run_id).info.experiment_id])
    assert [(r.info.run_id, r.info.status) for r in runs] == [(run_id, "FINISHED")]


@pytest.mark.slow
def test_a_checkpoint_that_fits_passes_the_check_untouched(tmp_path, prior_run):
    run_dir = tmp_path / "run"
    shutil.copytree(prior_run, run_dir)
    before = _digest(run_dir)
    cfg = validate(_plain(compose_smoke(run_dir, tmp_path / "cache", "motion=walk", "resume=true")))
    ckpt = max((run_dir / "checkpoints").glob("ckpt-*.pt"))
    assert preflight.resume_checkpoint(cfg, preflight.character_and_clips(cfg)) == ckpt
    preflight.check(cfg)
    assert _digest(run_dir) == before


def test_unreadable_run_file_is_named_on_resume(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "run.json").write_text('{"run_id": ')  # cut short
    code, err = run_main(tmp_path, capsys, "motion=walk", "resume=true", run_dir=run_dir)
    line = assert_refused(tmp_path, code, err, str(run_dir / "run.json"))
    assert line.endswith('not a run file ({"run_id": "<MLflow run id>"}); resume=true reads it')
    assert (run_dir / "run.json").read_text() == '{"run_id": '
    assert sorted(p.name for p in run_dir.iterdir()) == ["run.json"]


# h. A device that is not there -----------------------------------------------------------------------
@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (("runtime.learner_device=cuda",), "runtime.learner_device=cuda"),
        (("runtime=ray", "runtime.learner_gpus=1"), "runtime.learner_gpus=1"),
        (("runtime=ray", "runtime.worker_gpus=0.5"), "runtime.worker_gpus=0.5"),
    ],
)
def test_a_gpu_that_is_not_there_is_refused_before_anything_starts(tmp_path, capsys, overrides, key):
    code, err = run_main(tmp_path, capsys, "motion=walk", *overrides)
    line = assert_refused(tmp_path, code, err, key, "no GPU on this machine")
    assert line.startswith("config error: ")
    assert not (tmp_path / "run").exists()  # nothing written, no Ray started, no run in a store


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_a_warp_simulator_on_a_gpu_that_is_not_there_is_refused_before_anything_starts(tmp_path, capsys):
    pytest.importorskip("mujoco_warp")
    code, err = run_main(tmp_path, capsys, "motion=walk", "sim.backend=warp", "sim.device=cuda:1")
    line = assert_refused(tmp_path, code, err, "sim.device=cuda:1", "no such GPU on this machine")
    assert line.startswith("config error: ") and "sim.device=cpu" in line
    assert not (tmp_path / "run").exists()


def test_rough_terrain_on_the_warp_simulator_is_refused_in_one_line(tmp_path, capsys):
    pytest.importorskip("mujoco_warp")
    code, err = run_main(tmp_path, capsys, "motion=walk", "sim.backend=warp", "terrain.kind=rough")
    line = assert_refused(tmp_path, code, err, "terrain.kind", "height field")
    assert "sim.backend=mujoco" in line
    assert not (tmp_path / "run").exists()


# i. Stage specs, joint maps and resumed runs, refused before anything runs ----------------------------------
def test_a_bad_stage_spec_anywhere_in_the_chain_is_refused_before_any_stage_trains(tmp_path, capsys):
    """physicsvae needs demos (from a tracker) and then a simulation_layer stage: its broken need would be met only
    after the tracker and the demos had trained."""
    code, err = run_main(
        tmp_path,
        capsys,
        "motion=walk",
        "algo=physicsvae",
        '+stage_overrides.simulation_layer=["algo.needs.demos=nosuch"]',
    )
    line = assert_refused(tmp_path, code, err, "algo.needs.demos", "'nosuch'")
    assert line.startswith("config error: ")
    assert not (tmp_path / "run").exists()


def test_a_joint_map_onto_a_body_we_do_not_have_is_refused_and_the_readmes_override_composes(tmp_path, capsys):
    code, err = run_main(tmp_path, capsys, "motion=walk", "motion.joint_map={Hips: pelvis}")
    line = assert_refused(tmp_path, code, err, "motion.joint_map.Hips", "'pelvis' is not a body of the character")
    assert line.startswith("config error: ") and "root" in line  # the bodies it has are listed
    assert not (tmp_path / "run").exists()
    cfg = compose_smoke(tmp_path / "run", tmp_path / "cache", "motion.joint_map={Hips: root, LeftUpLeg: left_hip}")
    assert dict(_plain(cfg)["motion"]["joint_map"]) == {"Hips": "root", "LeftUpLeg": "left_hip"}


@pytest.mark.parametrize("gone", ["deleted", "never there"])
def test_resuming_a_run_the_store_does_not_have_is_refused(tmp_path, capsys, gone):
    from mlflow.tracking import MlflowClient

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    uri = f"sqlite:///{tmp_path / 'store.db'}"
    client = MlflowClient(uri)
    run_id = client.create_run(client.create_experiment("e", artifact_location=str(tmp_path / "a"))).info.run_id
    if gone == "deleted":
        client.delete_run(run_id)
    else:
        run_id = "0" * 32
    (run_dir / "run.json").write_text(json.dumps({"run_id": run_id}))
    code, err = run_main(tmp_path, capsys, "motion=walk", "resume=true", f"tracking.uri={uri}", run_dir=run_dir)
    line = assert_refused(tmp_path, code, err, str(run_dir / "run.json"), run_id, "is not in the store")
    assert "sqlite:///" in line
    assert sorted(p.name for p in run_dir.iterdir()) == ["run.json"]
    assert len(client.search_runs([client.get_experiment_by_name("e").experiment_id], run_view_type=3)) == 1


def test_a_replay_capacity_the_memory_cannot_hold_is_refused_before_anything_starts(tmp_path, capsys):
    code, err = run_main(tmp_path, capsys, "motion=walk", "algo.loop.replay_capacity=10000000000")
    line = assert_refused(tmp_path, code, err, "algo.loop.replay_capacity=10000000000", "GiB this machine has")
    assert line.startswith("config error: ") and "transitions fit" in line
    assert not (tmp_path / "run").exists()


def test_a_warp_gpu_the_ray_workers_cannot_see_or_warp_cannot_run_is_refused_before_anything_starts(
    tmp_path, capsys, monkeypatch
):
    """Under Ray a worker sees its one GPU as cuda:0, so cuda:1 would fail inside the actor; and warp-lang's CUDA 13
    binary sees no GPU under a driver older than R580 where torch sees one. This machine has no GPU: torch's and
    Warp's counts are stood in for (two GPUs for torch; none, then one, for Warp)."""
    pytest.importorskip("mujoco_warp")
    import warp

    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    code, err = run_main(tmp_path, capsys, "motion=walk", "runtime=ray", "sim.backend=warp", "sim.device=cuda:1")
    line = assert_refused(tmp_path, code, err, "sim.device=cuda:1", "under Ray a rollout worker sees only the GPU")
    assert line.startswith("config error: ") and "give sim.device=cuda" in line
    monkeypatch.setattr(warp, "get_cuda_device_count", lambda: 0)
    code, err = run_main(tmp_path, capsys, "motion=walk", "sim.backend=warp", "sim.device=cuda:1")
    line = assert_refused(tmp_path, code, err, "sim.device=cuda:1", "sees no CUDA device where torch sees 2")
    assert "needs an NVIDIA driver of R580 or newer" in line
    assert not (tmp_path / "run").exists()
