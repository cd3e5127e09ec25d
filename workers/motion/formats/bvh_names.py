"""Which joint of a BVH skeleton drives which of our bodies: the common naming conventions, then the skeleton.

A name is read without its namespace (`mixamorig:`), case, separators, a trailing number
(`Spine1`, `Neck1`, `spine.003`) or a leading `Bip01`/`Character1` word or Rigify layer
(`DEF-`, `ORG-`), with the side from a prefix or suffix: `LeftArm`, `Left_Arm`, `l_arm`,
`lShldr`, `LHipJoint`, `UpperArm_L`, `upperarm.l`, `ArmLeft`, `Bip01 L Thigh`, `DEF-thigh.L.001`
(the thigh's second segment: the first, `DEF-thigh.L`, comes first and is taken). Each of our
bodies takes the first joint, in hierarchy order, of its most preferred part (PARTS):

* root: Hips, Pelvis, Hip (without a side, as Daz's), Root; else the spine joint both thighs
  hang from (Rigify's metarig `spine`, its deform rig's `DEF-spine`).
* chest: of the spine joints (Spine, Chest, LowerBack, Abdomen, ...), the last one below which
  both arms and the neck branch off: Spine2 in Mixamo and LaFAN1, Spine1 in CMU, Chest2 in
  the mocap-bank files, Chest in Bandai-Namco's. Our chest carries the arms and the neck.
* neck: Neck (the first of Neck, Neck1), else Head, else the spine joint on from the chest
  (Rigify's `spine.004`); our neck body carries the head.
* shoulder (our upper arm): Arm, UpArm, UpperArm, Shldr, Humerus; else the joint of that side
  that is the elbow's parent. So "LeftShoulder" is the clavicle in Mixamo, CMU and LaFAN1
  (LeftShoulder -> LeftArm -> LeftForeArm, left unused), and the upper arm where the clavicle
  is called Collar (LeftCollar -> LeftShoulder -> LeftElbow, the mocap-bank/Biovision style).
* elbow: ForeArm, LowArm, LowerArm, Elbow. wrist: Hand, Wrist.
* hip (our thigh): UpLeg, UpperLeg, Thigh, Femur, Hip; else the knee's parent on that side.
  CMU's LHipJoint (a pelvis bone) is not a thigh.
* knee (our shin): LowLeg, LowerLeg, Shin, Calf, Knee, then Leg (Mixamo's and CMU's LeftLeg).
* ankle (our foot): Foot, Ankle; else the knee's first child on that side.

A user map (source joint name, case-insensitive, with or without its namespace -> our body)
comes first: the bodies it names take its joints, and those joints take part in nothing else.
"""

from __future__ import annotations

import re
from pathlib import Path

from workers.motion.errors import ClipError

SIDES = ("left", "right")
# Our body kinds -> source part names (lower case, no digits or separators), most preferred first.
PARTS: dict[str, tuple[str, ...]] = {
    "root": ("hips", "pelvis", "hip", "root"),
    "chest": ("spine", "chest", "upperchest", "lowerback", "upperback", "back", "abdomen", "torso", "thorax", "waist"),
    "neck": ("neck", "head"),
    "shoulder": ("arm", "uparm", "upperarm", "shldr", "humerus"),
    "elbow": ("forearm", "lowarm", "lowerarm", "elbow"),
    "wrist": ("hand", "wrist"),
    "hip": ("upleg", "upperleg", "thigh", "femur", "hip"),
    "knee": ("lowleg", "lowerleg", "shin", "calf", "knee", "leg"),
    "ankle": ("foot", "ankle"),
}
CENTRAL = ("root", "chest", "neck")
# Parts recognised with a side but matched to none of our bodies by name.
_OTHER_LIMB_PARTS = ("shoulder", "collar", "clavicle", "toe", "toebase", "toes")
_KNOWN_CENTRAL = {p for k in CENTRAL for p in PARTS[k]}
_SPINE = {(None, p) for p in PARTS["chest"]}
_KNOWN_LIMB = {p for k, v in PARTS.items() if k not in CENTRAL for p in v} | set(_OTHER_LIMB_PARTS)
_SIDE_WORDS = {"left": "left", "right": "right", "l": "left", "r": "right"}
# Bodies that may go without a source joint (a warning): ours carry the head, a face of a sphere.
MINOR_BODIES = ("neck",)


def _part(text: str) -> str:
    return re.sub(r"\d+$", "", text.lower())


def split_name(name: str) -> tuple[str | None, str]:
    """(side or None, part) of a source joint name: split_name("mixamorig:LeftForeArm") == ("left", "forearm")."""
    tokens = re.findall(r"[A-Za-z0-9]+", name.rsplit(":", 1)[-1])
    side = None
    for i, t in enumerate(tokens):  # a word of its own: "Bip01 L Thigh", "UpperArm_L", "Left Arm"
        if len(tokens) > 1 and t.lower() in _SIDE_WORDS:
            side, tokens = _SIDE_WORDS[t.lower()], tokens[:i] + tokens[i + 1 :]
            break
    variants = ["".join(tokens)]
    if len(tokens) > 1 and re.fullmatch(
        r"[A-Za-z]+\d+|mixamorig|armature|skeleton|rig|def|org", tokens[0], re.IGNORECASE
    ):
        variants.append("".join(tokens[1:]))  # Bip01 Pelvis, Character1_Hips, mixamorig_Hips, DEF-thigh.L
    fallback = None
    for text in variants:
        parses = [(side, text)] if side else [(None, text)]
        if side is None:
            low = text.lower()
            for word, s in sorted(_SIDE_WORDS.items(), key=lambda kv: -len(kv[0])):
                if low.startswith(word) and len(low) > len(word):
                    parses.append((s, text[len(word) :]))
                if low.endswith(word) and len(low) > len(word):
                    parses.append((s, text[: -len(word)]))
        for s, rest in parses:
            part = _part(rest)
            if (s is None and part in _KNOWN_CENTRAL) or (s is not None and part in _KNOWN_LIMB):
                return s, part
        if fallback is None:
            camel = re.match(r"(Left|Right|L|R)(?=[A-Z])", text)
            if side or camel is None:
                fallback = (side, _part(text))
            else:
                fallback = (_SIDE_WORDS[camel[1].lower()], _part(text[len(camel[1]) :]))
    return fallback if fallback is not None else (None, "")


def body_kind(body: str) -> tuple[str | None, str]:
    """(side, kind) of one of our bodies: body_kind("left_elbow") == ("left", "elbow")."""
    side, _, kind = body.partition("_")
    return (side, kind) if side in SIDES and kind else (None, body)


def match_joints(path: Path, joints: list, bodies: list[str], joint_map: dict[str, str] | None = None) -> dict:
    """Our body name -> index of its source joint (see the module doc); End Sites never match.

    joints: bvh.Joint list (.name, .parent, .end_site) in hierarchy order; joint_map: the user's
    source name -> body entries, applied before (and overriding) the conventions.
    """
    user = {str(k).lower(): v for k, v in (joint_map or {}).items()}
    unknown = sorted(set(user.values()) - set(bodies))
    if unknown:
        raise ClipError(path, f"joint_map targets {unknown} are not bodies of the character {bodies}")
    real = [j for j, jt in enumerate(joints) if not jt.end_site]
    out: dict[str, int] = {}
    for j in real:
        key = joints[j].name.lower()
        body = user.get(key, user.get(key.rsplit(":", 1)[-1]))
        if body is not None and body not in out:
            out[body] = j
    used = set(out.values())
    parsed = {j: split_name(joints[j].name) for j in real}

    def assign(body: str, j: int | None) -> None:
        if j is not None and body in bodies and body not in out and j not in used:
            out[body] = j
            used.add(j)

    def find(side: str | None, kind: str) -> int | None:
        for part in PARTS[kind]:
            for j in real:
                if parsed[j] == (side, part) and j not in used:
                    return j
        return None

    def sided(j: int, side: str) -> int | None:
        return j if j >= 0 and not joints[j].end_site and parsed[j][0] == side else None

    assign("root", find(None, "root"))
    for side in SIDES:
        for kind in ("hip", "knee", "ankle", "shoulder", "elbow", "wrist"):
            assign(f"{side}_{kind}", find(side, kind))
    for side in SIDES:  # the skeleton decides where the names do not
        if f"{side}_knee" in out:
            knee = out[f"{side}_knee"]
            assign(f"{side}_hip", sided(joints[knee].parent, side))
            kids = [c for c in real if joints[c].parent == knee and parsed[c][0] == side]
            assign(f"{side}_ankle", kids[0] if kids else None)
        if f"{side}_elbow" in out:
            assign(f"{side}_shoulder", sided(joints[out[f"{side}_elbow"]].parent, side))
    if "root" not in out and {"left_hip", "right_hip"} <= set(out):  # Rigify: spine is the hips
        hips = _common_ancestor(joints, out["left_hip"], out["right_hip"])
        assign("root", hips if hips is not None and parsed[hips] in _SPINE else None)
    assign("neck", find(None, "neck"))
    spine = [j for j in real if parsed[j][0] is None and parsed[j][1] in PARTS["chest"] and j not in used]
    if "chest" in bodies and "chest" not in out:
        above = [out[b] for b in ("left_shoulder", "right_shoulder", "neck") if b in out]
        branch = [j for j in spine if all(_is_below(joints, a, j) for a in above)]
        assign("chest", max(branch, key=lambda j: _depth(joints, j)) if branch and above else next(iter(spine), None))
    if "neck" not in out and "chest" in out:  # Rigify: the spine goes on past the chest (spine.004)
        assign("neck", next((j for j in spine if joints[j].parent == out["chest"]), None))
    return out


def _common_ancestor(joints: list, a: int, b: int) -> int | None:
    """The deepest joint above both a and b (None if they share none)."""
    above = set()
    while a >= 0:
        a = joints[a].parent
        above.add(a)
    while b >= 0 and b not in above:
        b = joints[b].parent
    return b if b >= 0 else None


def _is_below(joints: list, j: int, anc: int) -> bool:
    while j >= 0 and j != anc:
        j = joints[j].parent
    return j == anc


def _depth(joints: list, j: int) -> int:
    d = 0
    while joints[j].parent >= 0:
        j, d = joints[j].parent, d + 1
    return d


def unmatched(bodies_with_joints: list[str], src: dict) -> tuple[list[str], list[str]]:
    """(essential, minor) bodies driven by a joint that no source joint drives."""
    missing = [b for b in bodies_with_joints if b not in src]
    return [b for b in missing if b not in MINOR_BODIES], [b for b in missing if b in MINOR_BODIES]


def refuse_unmatched(path: Path, joints: list, missing: list[str]) -> None:
    """One ClipError naming the file, the bodies without a source joint and the file's joints."""
    names = [jt.name for jt in joints if not jt.end_site]
    shown = ", ".join(names[:40]) + (f", ... ({len(names)} joints)" if len(names) > 40 else "")
    raise ClipError(
        path,
        f"no source joint found for {', '.join(missing)}, which would stay at the identity rotation; "
        f"name their joints with motion.joint_map (--joint-map for `orchestrator.motion check`, joint_map= "
        f'in Python), e.g. {{"<source joint>": "{missing[0]}"}}. The file\'s joints: {shown}',
    )
