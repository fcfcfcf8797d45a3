"""Benchmark: the MAVLink output's work per frame, off the frame loop.

Reduces one published range map to DISTANCE_SENSOR (median and tile minimum) and to the 72
OBSTACLE_DISTANCE sectors, and prints ms/frame as a ratio to a plain memory copy of the range
map measured in the same run (these machines are noisy; ratios travel better than ms), and the
share of one CPU core it takes at 10 Hz (the output reduces one frame per message sent,
whatever the camera's frame rate).

    python3 bench/bench_mavlink.py [--repeat N] [--size WxH]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from timing import best_time  # noqa: E402
from uwcam.config import MavlinkConfig  # noqa: E402
from uwcam.drivers.base import Frame  # noqa: E402
from uwcam.optics.geometry import Intrinsics, pixel_rays  # noqa: E402
from uwcam.outputs.mavlink_measure import PixelRays, measure  # noqa: E402
from uwcam.runtime.published import Published  # noqa: E402
from uwcam.ranging.result import RangeResult  # noqa: E402


class _Profile:
    def __init__(self, intrinsics: Intrinsics) -> None:
        self.intrinsics = intrinsics
        self.lamp_position_m = (0.3, 0.0, 0.0)

    def camera_intrinsics(self) -> Intrinsics:
        return self.intrinsics


def published_frame(width: int, height: int) -> tuple[Published, _Profile]:
    """A seabed 2 m below, 5 % of the pixels invalid, 1 % noise."""
    rng = np.random.default_rng(1)
    intr = Intrinsics.from_fov(width, height, 70.0)
    r = (2.0 / pixel_rays(intr, height, width)[..., 2] * (1 + 0.01 * rng.standard_normal((height, width)))).astype(np.float32)
    r[rng.random((height, width)) < 0.05] = np.nan
    result = RangeResult(r, np.where(np.isfinite(r), 1e-4, np.nan).astype(np.float32), np.where(np.isfinite(r), 0, 1).astype(np.uint8))
    frame = Frame(np.zeros((1, 1, 3), np.uint16), 1, 0, 0.0)
    return Published(1, frame, result, 0, (0.0, 0.0, 0.0)), _Profile(intr)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=30)
    parser.add_argument("--size", default="1280x720")
    args = parser.parse_args()
    width, height = map(int, args.size.split("x"))
    published, profile = published_frame(width, height)
    copy_s, _ = best_time(lambda: published.result.range.copy(), args.repeat)
    print(f"{width}×{height} range map; memcopy {copy_s * 1e3:.3f} ms")
    cases = {
        "median, whole image": MavlinkConfig(),
        "median, centre quarter": MavlinkConfig(region=(width // 4, height // 4, width // 2, height // 2)),
        "minimum (8×8 tiles), whole image": MavlinkConfig(statistic="minimum", orientation="NONE"),
        "minimum + 72 obstacle sectors": MavlinkConfig(statistic="minimum", orientation="NONE", obstacle_distance=True),
    }
    for name, config in cases.items():
        rays = PixelRays()
        measure(published, config, profile, (0.0, 100.0), rays)  # rays computed once, as in the output
        best, median = best_time(lambda: measure(published, config, profile, (0.0, 100.0), rays), args.repeat)
        print(f"{name:36s} {best * 1e3:8.2f} ms (median {median * 1e3:.2f})  {best / copy_s:7.1f}× memcopy  "
              f"{100 * best * 10:5.1f} % of a core at 10 Hz")


if __name__ == "__main__":
    main()
