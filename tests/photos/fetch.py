"""Fetch the public photographs the real-photograph tests use into tests/photos/cache/ (not committed).

    .venv/bin/python tests/photos/fetch.py          # or: make photos (make test does it first)

The photograph is one file of OpenCV's own documentation, which PyPI ships inside the source
distribution of the OpenCV wheel this project pins (see tests/photos/README.md for the source,
the licence and what is in the photograph). ``pip download`` fetches that sdist (≈ 82 MB; pip
prepares its metadata, which installs scikit-build and cmake wheels into a throwaway build
environment, nothing into the venv); the photograph and OpenCV's LICENSE are extracted and the
photograph's SHA-256 is checked. Nothing is built.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

SDIST = "opencv-python-headless==5.0.0.93"
MEMBERS = {  # path inside the sdist's opencv/ folder → (file name in the cache, SHA-256 or None)
    "doc/tutorials/calib3d/interactive_calibration/images/dualCircles.jpg":
        ("dualCircles.jpg", "01097d85f908bba6965f81a2067863733683e34bc76bda090e2ddbf2393020b9"),
    "LICENSE": ("OPENCV_LICENSE", None),
}
CACHE = Path(__file__).resolve().parent / "cache"


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def fetch(cache: Path = CACHE) -> None:
    """Download the sdist of :data:`SDIST` with pip and extract :data:`MEMBERS` into ``cache``;
    raise RuntimeError naming the file whose SHA-256 differs."""
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary",
                        SDIST.split("==")[0], "-d", tmp, SDIST], check=True)
        (archive,) = Path(tmp).glob("*.tar.gz")
        with tarfile.open(archive) as tar:
            for name in tar.getnames():
                parts = name.split("/", 2)
                if len(parts) == 3 and parts[1] == "opencv" and parts[2] in MEMBERS:
                    out, digest = MEMBERS[parts[2]]
                    (cache / out).write_bytes(tar.extractfile(name).read())
                    if digest is not None and sha256(cache / out) != digest:
                        raise RuntimeError(f"{cache / out}: SHA-256 {sha256(cache / out)} is not the expected {digest}")
    missing = [out for out, _ in MEMBERS.values() if not (cache / out).exists()]
    if missing:
        raise RuntimeError(f"{archive.name} lacks {', '.join(missing)}")


if __name__ == "__main__":
    fetch()
    print(f"photographs in {CACHE}")
