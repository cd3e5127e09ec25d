"""The checks behind one-line refusals of bad input: checkpoints, character files, Ray addresses, MuJoCo's log."""

from __future__ import annotations

import logging
import zipfile

import mujoco
import numpy as np
import pytest
import torch

from orchestrator import checkpoint
from orchestrator.checkpoint import CheckpointError
from workers.body.character import Character, CharacterError


# Checkpoints ----------------------------------------------------------------------------------------
@pytest.fixture
def saved(tmp_path):
    state = {
        "loop": {"iteration": 3, "samples": 96},
        "method": {},
        "workers": [],
        "net": torch.nn.Linear(3, 4).state_dict(),
    }
    return checkpoint.save(tmp_path, 3, state)


def test_a_good_checkpoint_loads(saved):
    state = checkpoint.load(saved)
    checkpoint.check_layout(saved, state, ["net"])
    checkpoint.check_restore(saved, state, {"net": torch.nn.Linear(3, 4)})


SPOILED = [
    (
        "truncated",
        lambda p: p.write_bytes(p.read_bytes()[:300]),
        "truncated or corrupt (an incomplete zip archive of 300",
    ),
    ("text", lambda p: p.write_text("hello"), "not a PyTorch weights file (torch.save writes a zip archive"),
    ("tensor", lambda p: torch.save(torch.zeros(3), p), "not a checkpoint (it holds a Tensor, not a dict of states)"),
    ("pickled array", lambda p: torch.save({"x": np.zeros(3)}, p), "holds Python objects besides tensors"),
    ("other zip", lambda p: zipfile.ZipFile(p, "w").writestr("a.txt", "hi"), "not a PyTorch weights file (a zip"),
]


@pytest.mark.parametrize("case,spoil,message", SPOILED, ids=[s[0] for s in SPOILED])
def test_an_unusable_checkpoint_is_named_and_left_as_it_is(saved, case, spoil, message):
    spoil(saved)
    before = saved.read_bytes()
    with pytest.raises(CheckpointError) as e:
        checkpoint.load(saved)
    assert str(e.value).startswith(f"{saved}: {message}")
    assert "\n" not in str(e.value)
    assert saved.read_bytes() == before


def test_a_checkpoint_for_other_network_sizes_names_the_tensor_and_both_shapes(saved):
    state = checkpoint.load(saved)
    with pytest.raises(CheckpointError) as e:
        checkpoint.check_restore(saved, state, {"net": torch.nn.Linear(3, 8)})
    assert (
        str(e.value)
        == f"{saved}: net: size mismatch for weight: [4, 3] in the checkpoint, [8, 3] in this config's network"
    )
    with pytest.raises(CheckpointError, match=r"net: Missing key\(s\) in state_dict: \"0.weight\""):
        checkpoint.check_restore(saved, state, {"net": torch.nn.Sequential(torch.nn.Linear(3, 4))})
    with pytest.raises(CheckpointError, match=r"has no state for replay, vae \(a checkpoint of another method"):
        checkpoint.check_layout(saved, state, ["net", "replay", "vae"])


# Character files ------------------------------------------------------------------------------------
def test_character_file_errors_name_the_file(tmp_path):
    with pytest.raises(CharacterError, match=r"nope.xml: no such file$"):
        Character.load(tmp_path / "nope.xml")
    with pytest.raises(CharacterError, match=r": is a directory, not an MJCF file$"):
        Character.load(tmp_path)
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><body")
    with pytest.raises(CharacterError, match=r"broken.xml: not a loadable MJCF \(XML parse error"):
        Character.load(broken)


# Ray addresses ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "address,message",
    [
        ("127.0.0.1:1", "runtime.address=127.0.0.1:1: no Ray cluster at 127.0.0.1:1 (connection refused)"),
        ("ray://127.0.0.1:1", "runtime.address=ray://127.0.0.1:1: no Ray cluster at 127.0.0.1:1 (connection refused)"),
        ("127.0.0.1", "runtime.address=127.0.0.1: no port"),
        ("http://127.0.0.1:8265", "runtime.address=http://127.0.0.1:8265: not a Ray address"),
    ],
)
def test_a_ray_address_where_nothing_answers_is_named(address, message):
    from orchestrator.runtime.ray import AddressError, check_address

    with pytest.raises(AddressError) as e:
        check_address(address, timeout_s=5.0)
    assert str(e.value).startswith(message)


# MuJoCo's warnings ----------------------------------------------------------------------------------
def test_mujoco_warnings_are_logged_not_written_to_the_working_directory(character, tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    data = mujoco.MjData(character.model)
    data.qvel[:] = 1e30  # "Nan, Inf or huge value in QVEL": MuJoCo's default handler writes MUJOCO_LOG.TXT
    with caplog.at_level(logging.DEBUG, logger="workers.body.mujoco_log"):  # past the first few: debug
        mujoco.mj_step(character.model, data)
    assert data.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number > 0
    assert any("MuJoCo: Nan, Inf or huge value in QVEL" in r.getMessage() for r in caplog.records)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
