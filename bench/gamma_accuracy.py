"""Accuracy of an ordinary camera: 16-bit linear vs 8-bit sRGB vs 8-bit sRGB JPEG, in jerlov-IB.

For each camera, calibrates in the simulated water (grey plate with black patch at 1 m and 2 m,
four frames per distance, fixed exposure; the 8-bit sRGB cameras on frames linearised through
the sRGB curve, which the profile then carries), then ranges the brick scene (grey material,
lamp 0.3 m to the side) at 1, 2, 3 and 5 m over several noisy frames, backscatter compensated
with two lamp-lit open-water frames at the same exposure, and prints, per range:
the median absolute range error in % of the true range, the fraction of pixels with a range,
and the sd and mean of z = (estimate − truth)/σ over the pixels ranged (the goal for an honest
σ: sd 0.8–1.25). A row takes the sRGB camera's codes as linear light, as uwcam did
before response curves: what the curve corrects. The last rows send the sRGB camera's frames
through a real RTSP server (gst-rtsp-server, x264 at 15 frames/s, tests/rtsp_server.py) and the
``stream`` driver, at 4 and 0.3 Mbit/s (at 320×240 that is 3.5 and 0.26 bit per pixel per frame;
a 1080p30 stream at 8 Mbit/s has 0.13).

    python3 bench/gamma_accuracy.py [--size 320x240] [--frames 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.ranging.images import range_images  # noqa: E402
from uwcam.simulation import CameraModel, Lamp, SimulatedWorld, water_preset  # noqa: E402
from uwcam.simulation.tank import calibrate_in_simulation  # noqa: E402

LAMP = Lamp(position=(0.3, 0.0, 0.0))
WATER = "jerlov-IB"
CAMERAS = {
    "16-bit linear": dict(bits=16),
    "8-bit sRGB": dict(bits=8, response="srgb"),
    "8-bit sRGB JPEG q90": dict(bits=8, response="srgb", jpeg_quality=90),
    "8-bit sRGB, curve ignored": dict(bits=8, response="srgb"),
}
STREAMS = {  # the 8-bit sRGB camera's frames through a real RTSP server (x264) and the stream driver
    "8-bit sRGB RTSP H.264 4 Mbit/s": 4000,
    "8-bit sRGB RTSP H.264 0.3 Mbit/s": 300,
}
SERVER = os.path.join(os.path.dirname(__file__), "..", "tests", "rtsp_server.py")


def through_rtsp(frames: list, bitrate_kbps: int) -> list:
    """The frames as the stream driver receives them from gst-rtsp-server (H.264, x264 at 15 frames/s)."""
    import select
    import socket
    import subprocess
    import tempfile

    from uwcam.drivers.base import CameraSettings
    from uwcam.drivers.stream import StreamCamera

    with tempfile.TemporaryDirectory() as tmp, socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        path = os.path.join(tmp, "frames.npy")
        np.save(path, np.stack(frames))
        proc = subprocess.Popen([sys.executable, SERVER, str(port), path, "h264", str(bitrate_kbps)],
                                stdout=subprocess.PIPE, text=True)
        try:
            select.select([proc.stdout], [], [], 30.0)
            assert proc.stdout.readline().startswith("ready"), "the RTSP server did not start"
            cam = StreamCamera(f"rtsp://127.0.0.1:{port}/cam", open_timeout_s=10.0)
            cam.open()
            cam.configure(CameraSettings())
            got = [cam.read(10.0).data for _ in range(len(frames) + 15)][15:]  # past the first GOP's ramp-up
            cam.close()
            return got
        finally:
            proc.terminate()
            proc.wait(10)
RANGES = (1.0, 2.0, 3.0, 5.0)


def measure(label: str, camera: dict, size: tuple[int, int], frames: int, bitrate_kbps: int | None = None) -> dict:
    water = water_preset(WATER, [675.0, 575.0, 475.0])
    profile = calibrate_in_simulation(water, LAMP, size, CameraModel(**camera), frames_per_distance=4,
                                      linearise="ignored" not in label)
    rows = {}
    for distance in RANGES:
        world = SimulatedWorld(scene="brick", distance=distance, size=size, water=water, lamp=LAMP,
                               camera=CameraModel(**camera), material="grey", seed=11)
        open_water = SimulatedWorld(scene="open-water", distance=distance, size=size, water=water, lamp=LAMP,
                                    camera=CameraModel(**camera), fixed_exposure=world.exposure, seed=6)
        water_frames = np.stack([open_water.frame(k) for k in range(2)])
        rel, z, valid = [], [], []
        images = [world.frame(k) for k in range(frames)]
        if bitrate_kbps is not None:
            images = through_rtsp(images, bitrate_kbps)
        for image in images:
            result = range_images(profile, [image], compensate=True, open_water=water_frames)
            truth = world.camera_range
            ok = np.isfinite(result.range) & (result.variance > 0)
            valid.append(ok.mean())
            err = result.range[ok].astype(np.float64) - truth[ok]
            rel.append(np.abs(err) / truth[ok])
            z.append(err / np.sqrt(result.variance[ok].astype(np.float64)))
        rel_all, z_all = np.concatenate(rel), np.concatenate(z)
        rows[f"{distance:g}"] = {"median_error_pct": float(100 * np.median(rel_all)) if rel_all.size else float("nan"),
                                 "valid": float(np.mean(valid)), "z_sd": float(np.std(z_all)) if z_all.size else float("nan"),
                                 "z_mean": float(np.mean(z_all)) if z_all.size else float("nan")}
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--json")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    results = {}
    print(f"{WATER}, brick scene (grey), {size[0]}x{size[1]}, {args.frames} frames per range")
    print(f"{'camera':22s} {'range':>6s} {'median |err|':>13s} {'valid':>6s} {'z sd':>6s} {'z mean':>7s}")
    for label, camera in CAMERAS.items():
        results[label] = measure(label, camera, size, args.frames)
        for r, row in results[label].items():
            print(f"{label:22s} {r + ' m':>6s} {row['median_error_pct']:12.2f}% {row['valid']:6.1%} "
                  f"{row['z_sd']:6.2f} {row['z_mean']:+7.2f}", flush=True)
    for label, bitrate in STREAMS.items():
        results[label] = measure(label, CAMERAS["8-bit sRGB"], size, args.frames, bitrate)
        for r, row in results[label].items():
            print(f"{label:22s} {r + ' m':>6s} {row['median_error_pct']:12.2f}% {row['valid']:6.1%} "
                  f"{row['z_sd']:6.2f} {row['z_mean']:+7.2f}", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
