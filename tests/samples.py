"""Third-party motion files the tests import: fetched by `make samples` (part of `make setup`).

Both come from source distributions on PyPI (their wheels leave the files out), each kept with
the package's LICENSE; what a new user brings from elsewhere, written by nobody here.

* `bvhtoolbox` 0.1.3 (MIT), tests/example_files/: a Mixamo export (`mixamorig:` names, 69
  frames) and a mocap-bank clip (Collar/Shoulder/Elbow/Wrist and Hip/Knee/Ankle names, 455
  frames), both at 30 Hz and in centimetres.
* `bvhtools` 1.6.0 (MIT), testBvhFiles/: test.bvh, a LaFAN1 clip (Ubisoft La Forge's data set,
  which the package redistributes; its skeleton to the hundredth of a millimetre: Hips, LeftUpLeg,
  LeftLeg, LeftFoot, LeftToe, ..., centimetres, every bone along its joint's x axis), 7184 frames
  at 30 Hz (4 minutes); test3.bvh, a skeleton with Rigify metarig names (pelvis, spine,
  spine.001, neck, shoulder.L, upper_arm.L, forearm.L, thigh.L, shin.L, foot.L; metres, position
  channels on every joint, as Blender exports), 3089 frames at 24 Hz (2 minutes).

    python -m tests.samples          # fetch into .cache/samples/ (again only if missing)
"""

from __future__ import annotations

import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / ".cache" / "samples"
# package -> (version, folder in its sdist, files kept)
SDISTS = {
    "bvhtoolbox": ("0.1.3", "tests/example_files", ("test_freebvh.bvh", "test_mocapbank.bvh")),
    "bvhtools": ("1.6.0", "testBvhFiles", ("test.bvh", "test3.bvh")),
}
BVH_DIR = SAMPLES / "bvhtoolbox-0.1.3"
BVHTOOLS_DIR = SAMPLES / "bvhtools-1.6.0"
FETCH = "make samples (or: python -m tests.samples)"


def fetch(package: str = "bvhtoolbox") -> Path:
    """Download a package's sdist with pip (the configured index) and keep its BVH files and licence."""
    version, folder, files = SDISTS[package]
    dest = SAMPLES / f"{package}-{version}"
    if all((dest / f).is_file() for f in files):
        return dest
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:"]
        subprocess.run([*cmd, f"{package}=={version}", "--dest", tmp], check=True)
        (sdist,) = Path(tmp).glob(f"{package}-{version}.tar.gz")
        wanted = {f"{package}-{version}/{folder}/{f}": f for f in files}
        wanted[f"{package}-{version}/LICENSE"] = "LICENSE"
        dest.mkdir(parents=True, exist_ok=True)
        with tarfile.open(sdist) as tar:
            for member, name in wanted.items():
                src = tar.extractfile(member)
                if src is None:
                    raise FileNotFoundError(f"{sdist.name} has no {member}")
                (dest / name).write_bytes(src.read())
    return dest


if __name__ == "__main__":
    for name in SDISTS:
        print(f"BVH samples in {fetch(name).relative_to(ROOT)}")
