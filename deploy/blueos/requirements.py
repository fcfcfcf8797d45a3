"""Print the runtime requirements to install in the container image for one architecture.

Usage: python deploy/blueos/requirements.py TARGETARCH   (amd64, arm64 or arm, as buildx names them)

Read from pyproject.toml so the image never drifts from the package. On 32-bit ARM (the
Raspberry Pi's 32-bit BlueOS image) PyPI has no numba wheels (uwcam then uses its numpy path),
no genicam wheels (so no harvesters: GigE/USB3 Vision cameras go through Aravis), and
pymavlink's fastcrc has none either (pymavlink then computes checksums in Python; it is
installed on its own, without dependencies, by the Dockerfile).
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

ARM32_SKIP = {"numba", "harvesters", "pymavlink"}
# Optional parts the vehicle's image carries: plots of a tank calibration made from the page, and
# remote monitoring on Zenoh. Not "cluster": a vehicle does not reprocess dives on a Dask cluster.
IMAGE_EXTRAS = ("reports", "zenoh")


def requirements(arch: str, pyproject: Path) -> list[str]:
    if arch not in ("amd64", "arm64", "arm"):
        raise SystemExit(f"unknown target architecture '{arch}'; expected amd64, arm64 or arm")
    project = tomllib.loads(pyproject.read_text())["project"]
    deps = list(project["dependencies"])
    for extra in IMAGE_EXTRAS:
        deps += project["optional-dependencies"][extra]
    skip = ARM32_SKIP if arch == "arm" else set()
    return [d for d in deps if re.split(r"[<>=!~\[; ]", d, maxsplit=1)[0].lower().replace("_", "-") not in skip]


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__.strip().splitlines()[2])
    print("\n".join(requirements(sys.argv[1], Path(__file__).resolve().parents[2] / "pyproject.toml")))
