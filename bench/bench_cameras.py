"""Benchmark: frames/s and per-frame cost of each camera driver under supervision, beside the
raw producer loop of the same source measured in the same run.

Raw loops: harvesters fetch + copy (GenTL producer simulator), Aravis stream pop + copy
(Fake camera), OpenCV VideoCapture.read on a
video file (the V4L2 driver's code path here), the simulator's frame(), reading replay files.
Supervised: SupervisedCamera(driver) with a consumer calling get(). CPU ms/frame is process
CPU time (both threads) per delivered frame.

    python3 bench/bench_cameras.py [--seconds S]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import cv2
import genicam
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.drivers.base import CameraSettings  # noqa: E402
from uwcam.drivers.genicam import GenTLCamera  # noqa: E402
from uwcam.drivers.replay import ReplayCamera  # noqa: E402
from uwcam.drivers.sim import SimulatedCamera, SimulatedRig  # noqa: E402
from uwcam.drivers.supervisor import SupervisedCamera  # noqa: E402
from uwcam.drivers.v4l2 import V4L2Camera  # noqa: E402
from uwcam.imaging.imageio import read_frame  # noqa: E402

VIKY = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")


def measure(loop, seconds):
    """(frames/s, CPU ms per frame) of ``loop()`` called until ``seconds`` pass; loop returns frames done."""
    t0, c0 = time.perf_counter(), time.process_time()
    frames = 0
    while time.perf_counter() - t0 < seconds:
        frames += loop()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return frames / wall, 1e3 * cpu / max(frames, 1)


def supervised(driver, seconds, settings=None):
    with SupervisedCamera(driver, settings, queue_size=8, read_timeout_s=2.0) as cam:
        cam.get(10.0)
        return measure(lambda: 1 if cam.get(5.0) is not None else 0, seconds)


def raw_gentl(seconds):
    from harvesters.core import Harvester

    h = Harvester()
    h.add_file(VIKY)
    h.update()
    ia = h.create(0)
    ia.start()
    try:
        def one():
            with ia.fetch(timeout=3) as buf:
                c = buf.payload.components[0]
                c.data.reshape(c.height, c.width, -1)[:, :, :3].copy()
            return 1
        one()
        return measure(one, seconds)
    finally:
        ia.stop()
        ia.destroy()
        h.reset()


def raw_aravis(seconds):
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    Aravis.enable_interface("Fake")
    cam = Aravis.Camera.new("Fake_1")
    cam.set_pixel_format_from_string("RGB8")
    cam.set_frame_rate(200.0)
    stream = cam.create_stream(None, None)
    for _ in range(8):
        stream.push_buffer(Aravis.Buffer.new_allocate(cam.get_payload()))
    cam.start_acquisition()
    try:
        def one():
            buf = stream.timeout_pop_buffer(2_000_000)
            if buf is None:
                return 0
            np.frombuffer(buf.get_data(), np.uint8).reshape(buf.get_image_height(), buf.get_image_width(), 3).copy()
            stream.push_buffer(buf)
            return 1
        one()
        return measure(one, seconds)
    finally:
        cam.stop_acquisition()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0)
    args = parser.parse_args()
    s = args.seconds
    rows = []

    rows.append(("GenTL (harvesters, viky.cti)", raw_gentl(s),
                 supervised(GenTLCamera(cti=VIKY), s, CameraSettings(pixel_format="RGBa8"))))

    from uwcam.drivers.aravis import AravisCamera

    rows.append(("Aravis Fake camera (512x512 RGB8)", raw_aravis(s),
                 supervised(AravisCamera(fake=True, device_id="Fake_1"), s, CameraSettings(pixel_format="RGB8", frame_rate=200.0))))

    with tempfile.TemporaryDirectory() as tmp:
        video = os.path.join(tmp, "clip.avi")
        writer = cv2.VideoWriter(video, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
        rng = np.random.default_rng(0)
        for _ in range(60):
            writer.write(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8))
        writer.release()
        cap = cv2.VideoCapture(video)

        def raw_video():
            ok, bgr = cap.read()
            if not ok:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                ok, bgr = cap.read()
            cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            return 1

        raw = measure(raw_video, s)
        cap.release()

        class LoopingFile(V4L2Camera):  # the V4L2 driver's own code on a file, rewound at the end
            def read(self, timeout_s):
                if self._cap.get(cv2.CAP_PROP_POS_FRAMES) >= self._cap.get(cv2.CAP_PROP_FRAME_COUNT):
                    self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                return super().read(timeout_s)

        rows.append(("V4L2 driver via OpenCV (file backend)", raw, supervised(LoopingFile(device=video, api="any"), s)))

        folder = os.path.join(tmp, "frames")
        os.mkdir(folder)
        for k in range(20):
            np.save(os.path.join(folder, f"{k:03d}.npy"), rng.integers(0, 65535, (720, 1280, 3), dtype=np.uint16))
        files = sorted(os.listdir(folder))
        index = iter(range(10**9))
        raw = measure(lambda: (read_frame(os.path.join(folder, files[next(index) % len(files)])), 1)[1], s)
        rows.append(("replay (1280x720x3 uint16 .npy)", raw, supervised(ReplayCamera(folder, fps=1000.0), s)))

    rig = SimulatedRig(size=(1280, 720))
    world = rig.world
    mean, std = rig.expected()
    out = np.empty(mean.shape, np.uint16)
    counter = iter(range(1, 10**9))
    raw = measure(lambda: (world.camera.digitise(mean, std, 0, next(counter), out), 1)[1], s)
    rows.append(("sim (1280x720x3, static scene)", raw, supervised(SimulatedCamera(rig, fps=1000.0), s)))

    print(f"{'driver':40s} {'raw fps':>8s} {'raw ms':>7s} {'driver fps':>10s} {'driver ms':>9s} {'fps ratio':>9s} {'overhead ms':>11s}")
    for name, (rf, rc), (df, dc) in rows:
        print(f"{name:40s} {rf:8.1f} {rc:7.2f} {df:10.1f} {dc:9.2f} {df / rf:9.2f} {dc - rc:11.2f}")
    print("ms: process CPU per frame. GenTL's simulator paces itself at its AcquisitionFrameRate; the others run flat out.")


if __name__ == "__main__":
    main()
