"""Third-party motion files the tests import: fetched by `make samples` (part of `make setup`).

The BVH files come from the source distribution of `bvhtoolbox` on PyPI (MIT licence, its
LICENSE is kept beside them); its wheel leaves them out. They are a Mixamo export
(`mixamorig:` names, 69 frames) and a mocap-bank clip (Collar/Shoulder/Elbow/Wrist and
Hip/Knee/Ankle names, 455 frames), both at 30 Hz and in centimetres: what a new user brings
from elsewhere, written by nobody here.

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
PACKAGE, VERSION = "bvhtoolbox", "0.1.3"
BVH_DIR = SAMPLES / f"{PACKAGE}-{VERSION}"
BVH_FILES = ("test_freebvh.bvh", "test_mocapbank.bvh")
FETCH = "make samples (or: python -m tests.samples)"


def fetch(dest: Path = BVH_DIR) -> Path:
    """Download the sdist with pip (the configured index) and keep its BVH files and licence."""
    if all((dest / f).is_file() for f in BVH_FILES):
        return dest
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:"]
        subprocess.run([*cmd, f"{PACKAGE}=={VERSION}", "--dest", tmp], check=True)
        (sdist,) = Path(tmp).glob(f"{PACKAGE}-{VERSION}.tar.gz")
        wanted = {f"{PACKAGE}-{VERSION}/tests/example_files/{f}": f for f in BVH_FILES}
        wanted[f"{PACKAGE}-{VERSION}/LICENSE"] = "LICENSE"
        dest.mkdir(parents=True, exist_ok=True)
        with tarfile.open(sdist) as tar:
            for member, name in wanted.items():
                src = tar.extractfile(member)
                if src is None:
                    raise FileNotFoundError(f"{sdist.name} has no {member}")
                (dest / name).write_bytes(src.read())
    return dest


if __name__ == "__main__":
    print(f"BVH samples in {fetch().relative_to(ROOT)}")
