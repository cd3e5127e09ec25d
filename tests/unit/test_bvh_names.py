"""Which source joint drives which body of ours, on the hierarchies of real exports.

Mixamo, CMU (cgspeed), LaFAN1, mocap-bank, Biovision, Bandai-Namco, Daz, 3ds Max biped, Unreal,
Blender, Rigify (metarig and deform bones) and OpenNI skeletons, written as outlines from the
files' HIERARCHY.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from workers.motion.formats import bvh
from workers.motion.formats.bvh_names import match_joints, split_name

LIMBS = ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")


# ----------------------------------------------------------------------------
def skeleton(spec: str, sides: tuple[str, str]) -> list[bvh.Joint]:
    """Joints from an indented outline. The subtree of a line with '<' (the side: Left, L, l...) or
    '!' (its first letter: CMU's LHipJoint) is repeated for both sides."""
    lines = [line for line in textwrap.dedent(spec).splitlines() if line.strip()]

    def indent(line: str) -> int:
        return len(line) - len(line.lstrip())

    out, i = [], 0
    while i < len(lines):
        if "<" in lines[i] or "!" in lines[i]:
            j = next((k for k in range(i + 1, len(lines)) if indent(lines[k]) <= indent(lines[i])), len(lines))
            out += [line.replace("<", s).replace("!", s[0]) for s in sides for line in lines[i:j]]
        else:
            j = i + 1
            out.append(lines[i])
        i = j
    joints, stack = [], []  # stack: (indent, index)
    for line in out:
        while stack and stack[-1][0] >= indent(line):
            stack.pop()
        joints.append(bvh.Joint(line.strip(), stack[-1][1] if stack else -1))
        stack.append((indent(line), len(joints) - 1))
    return joints


CMU = """
    Hips
     !HipJoint
      <UpLeg
       <Leg
        <Foot
         <ToeBase
     LowerBack
      Spine
       Spine1
        Neck
         Neck1
          Head
        <Shoulder
         <Arm
          <ForeArm
           <Hand
            <FingerBase
            !Thumb
"""
CONVENTIONS = {
    # name: (outline, sides, expected: our body kind -> source name, '<' for the side)
    "mixamo": (
        """
        mixamorig:Hips
         mixamorig:Spine
          mixamorig:Spine1
           mixamorig:Spine2
            mixamorig:Neck
             mixamorig:Head
              mixamorig:HeadTop_End
            mixamorig:<Shoulder
             mixamorig:<Arm
              mixamorig:<ForeArm
               mixamorig:<Hand
                mixamorig:<HandIndex1
         mixamorig:<UpLeg
          mixamorig:<Leg
           mixamorig:<Foot
            mixamorig:<ToeBase
        """,
        ("Left", "Right"),
        {"root": "mixamorig:Hips", "chest": "mixamorig:Spine2", "neck": "mixamorig:Neck",
         "shoulder": "mixamorig:<Arm", "elbow": "mixamorig:<ForeArm", "wrist": "mixamorig:<Hand",
         "hip": "mixamorig:<UpLeg", "knee": "mixamorig:<Leg", "ankle": "mixamorig:<Foot"},
    ),
    "cmu": (
        CMU,
        ("Left", "Right"),
        {"root": "Hips", "chest": "Spine1", "neck": "Neck", "shoulder": "<Arm", "elbow": "<ForeArm",
         "wrist": "<Hand", "hip": "<UpLeg", "knee": "<Leg", "ankle": "<Foot"},
    ),
    "mocap_bank": (
        """
        Hips
         Chest
          Chest2
           <Collar
            <Shoulder
             <Elbow
              <Wrist
           Neck
            Head
         <Hip
          <Knee
           <Ankle
        """,
        ("Left", "Right"),
        {"root": "Hips", "chest": "Chest2", "neck": "Neck", "shoulder": "<Shoulder", "elbow": "<Elbow",
         "wrist": "<Wrist", "hip": "<Hip", "knee": "<Knee", "ankle": "<Ankle"},
    ),
    "biovision": (
        """
        Hips
         Chest
          Neck
           Head
          <Collar
           <UpArm
            <LowArm
             <Hand
         <UpLeg
          <LowLeg
           <Foot
        """,
        ("Left", "Right"),
        {"root": "Hips", "chest": "Chest", "neck": "Neck", "shoulder": "<UpArm", "elbow": "<LowArm",
         "wrist": "<Hand", "hip": "<UpLeg", "knee": "<LowLeg", "ankle": "<Foot"},
    ),
    "bandai_namco": (
        """
        Hips
         Spine
          Chest
           Neck
            Head
           Shoulder_<
            UpperArm_<
             LowerArm_<
              Hand_<
         UpperLeg_<
          LowerLeg_<
           Foot_<
            Toes_<
        """,
        ("L", "R"),
        {"root": "Hips", "chest": "Chest", "neck": "Neck", "shoulder": "UpperArm_<", "elbow": "LowerArm_<",
         "wrist": "Hand_<", "hip": "UpperLeg_<", "knee": "LowerLeg_<", "ankle": "Foot_<"},
    ),
    "daz": (
        """
        hip
         abdomen
          chest
           neck
            head
           <Collar
            <Shldr
             <ForeArm
              <Hand
         <Buttock
          <Thigh
           <Shin
            <Foot
        """,
        ("l", "r"),
        {"root": "hip", "chest": "chest", "neck": "neck", "shoulder": "<Shldr", "elbow": "<ForeArm",
         "wrist": "<Hand", "hip": "<Thigh", "knee": "<Shin", "ankle": "<Foot"},
    ),
    "3ds_max_biped": (
        """
        Bip01
         Bip01 Pelvis
          Bip01 Spine
           Bip01 Spine1
            Bip01 Neck
             Bip01 Head
             Bip01 < Clavicle
              Bip01 < UpperArm
               Bip01 < Forearm
                Bip01 < Hand
           Bip01 < Thigh
            Bip01 < Calf
             Bip01 < Foot
        """,
        ("L", "R"),
        {"root": "Bip01 Pelvis", "chest": "Bip01 Spine1", "neck": "Bip01 Neck", "shoulder": "Bip01 < UpperArm",
         "elbow": "Bip01 < Forearm", "wrist": "Bip01 < Hand", "hip": "Bip01 < Thigh", "knee": "Bip01 < Calf",
         "ankle": "Bip01 < Foot"},
    ),
    "unreal": (
        """
        root
         pelvis
          spine_01
           spine_02
            spine_03
             clavicle_<
              upperarm_<
               upperarm_twist_01_<
               lowerarm_<
                hand_<
             neck_01
              head
          thigh_<
           calf_<
            foot_<
             ball_<
        """,
        ("l", "r"),
        {"root": "pelvis", "chest": "spine_03", "neck": "neck_01", "shoulder": "upperarm_<",
         "elbow": "lowerarm_<", "wrist": "hand_<", "hip": "thigh_<", "knee": "calf_<", "ankle": "foot_<"},
    ),
    "blender": (
        """
        hips
         spine
          chest
           neck
            head
           shoulder.<
            upper_arm.<
             forearm.<
              hand.<
         thigh.<
          shin.<
           foot.<
            toe.<
        """,
        ("L", "R"),
        {"root": "hips", "chest": "chest", "neck": "neck", "shoulder": "upper_arm.<", "elbow": "forearm.<",
         "wrist": "hand.<", "hip": "thigh.<", "knee": "shin.<", "ankle": "foot.<"},
    ),
    "lafan1": (  # the bvhtools sample's hierarchy (test_bvh_conventions.py imports the file itself)
        """
        Hips
         <UpLeg
          <Leg
           <Foot
            <Toe
         Spine
          Spine1
           Spine2
            Neck
             Head
            <Shoulder
             <Arm
              <ForeArm
               <Hand
        """,
        ("Left", "Right"),
        {"root": "Hips", "chest": "Spine2", "neck": "Neck", "shoulder": "<Arm", "elbow": "<ForeArm",
         "wrist": "<Hand", "hip": "<UpLeg", "knee": "<Leg", "ankle": "<Foot"},
    ),
    "rigify_metarig": (  # spine is the hips, spine.003 the chest, spine.004 the neck, spine.006 the head
        """
        spine
         spine.001
          spine.002
           spine.003
            spine.004
             spine.005
              spine.006
               face
            shoulder.<
             upper_arm.<
              forearm.<
               hand.<
                palm.01.<
            breast.<
         pelvis.<
         thigh.<
          shin.<
           foot.<
            toe.<
            heel.02.<
        """,
        ("L", "R"),
        {"root": "spine", "chest": "spine.003", "neck": "spine.004", "shoulder": "upper_arm.<",
         "elbow": "forearm.<", "wrist": "hand.<", "hip": "thigh.<", "knee": "shin.<", "ankle": "foot.<"},
    ),
    "rigify_deform": (  # the generated rig's DEF- bones, limbs in two segments
        """
        DEF-spine
         DEF-spine.001
          DEF-spine.002
           DEF-spine.003
            DEF-spine.004
             DEF-spine.005
              DEF-spine.006
            DEF-shoulder.<
             DEF-upper_arm.<
              DEF-upper_arm.<.001
               DEF-forearm.<
                DEF-forearm.<.001
                 DEF-hand.<
            DEF-breast.<
         DEF-pelvis.<
         DEF-thigh.<
          DEF-thigh.<.001
           DEF-shin.<
            DEF-shin.<.001
             DEF-foot.<
              DEF-toe.<
        """,
        ("L", "R"),
        {"root": "DEF-spine", "chest": "DEF-spine.003", "neck": "DEF-spine.004", "shoulder": "DEF-upper_arm.<",
         "elbow": "DEF-forearm.<", "wrist": "DEF-hand.<", "hip": "DEF-thigh.<", "knee": "DEF-shin.<",
         "ankle": "DEF-foot.<"},
    ),
    "openni": (  # no clavicle: the shoulder is the upper arm
        """
        pelvis
         torso
          neck
           head
          <_shoulder
           <_elbow
            <_hand
         <_hip
          <_knee
           <_foot
        """,
        ("l", "r"),
        {"root": "pelvis", "chest": "torso", "neck": "neck", "shoulder": "<_shoulder", "elbow": "<_elbow",
         "wrist": "<_hand", "hip": "<_hip", "knee": "<_knee", "ankle": "<_foot"},
    ),
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(CONVENTIONS))
def test_naming_conventions(character, name):
    spec, sides, expected = CONVENTIONS[name]
    joints = skeleton(spec, sides)
    got = {b: joints[j].name for b, j in match_joints(Path(name), joints, character.body_names).items()}
    want = {}
    for kind, src in expected.items():
        if kind in LIMBS:
            want.update(
                {f"{side}_{kind}": src.replace("<", s) for side, s in zip(("left", "right"), sides, strict=True)}
            )
        else:
            want[kind] = src
    assert got == want  # e.g. CMU's LHipJoint (a pelvis bone) and Mixamo's LeftShoulder (a clavicle) unused


def test_split_name():
    assert split_name("mixamorig:LeftForeArm") == ("left", "forearm")
    assert split_name("LHipJoint") == ("left", "hipjoint") and split_name("lShldr") == ("left", "shldr")
    assert split_name("Bip01 R Thigh") == ("right", "thigh") and split_name("upper_arm.L") == ("left", "upperarm")
    assert split_name("LowerBack") == (None, "lowerback") and split_name("Spine1") == (None, "spine")
    assert split_name("hip") == (None, "hip") and split_name("RightHip") == ("right", "hip")
    assert split_name("DEF-thigh.L") == ("left", "thigh") and split_name("DEF-thigh.L.001") == ("left", "thigh")
    assert split_name("ORG-spine.003") == (None, "spine") and split_name("spine.004") == (None, "spine")


def test_a_shoulder_without_an_elbow_below_is_not_guessed(character):
    """mocap-bank's LeftShoulder is the upper arm because LeftElbow hangs from it: without the
    elbow it stays unmatched (the load refuses), and naming the elbow in the map settles both."""
    joints = skeleton(CONVENTIONS["mocap_bank"][0].replace("<Elbow", "<Segment"), ("Left", "Right"))
    src = match_joints(Path("x"), joints, character.body_names)
    assert {"left_shoulder", "left_elbow", "right_shoulder", "right_elbow"}.isdisjoint(src)
    src = match_joints(Path("x"), joints, character.body_names, {"leftsegment": "left_elbow"})
    assert joints[src["left_elbow"]].name == "LeftSegment" and joints[src["left_shoulder"]].name == "LeftShoulder"
    assert "right_shoulder" not in src
