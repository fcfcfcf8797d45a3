"""Reprocessing throughput: frames/s in one process vs a local Dask cluster, and what that means
for a campaign of many dives.

A short dive is recorded from the simulated rig by the daemon's own recorder, then lengthened
to ``--frames`` frames by repeating its messages at later times (reprocessing cost does not
depend on the pixels' values), and reprocessed (1) in this process, (2) on a local Dask cluster
of ``--workers`` worker processes (its start-up counted separately). Figures are wall-clock on
whatever machine runs this; on a shared machine compare the ratio, not the absolute numbers.

    .venv/bin/python bench/bench_reprocess.py --size 640x480 --frames 100 --workers 2
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from uwcam.recording import format as rec  # noqa: E402
from uwcam.config import CameraConfig, DaemonConfig, DeviceConfig, RecordingConfig  # noqa: E402
from uwcam.runtime.daemon import Daemon  # noqa: E402
from uwcam.recording.reprocess import plan, process_part, ranged_frame_count, reprocess  # noqa: E402


def record_dive(path: str, size: tuple[int, int], frames: int) -> None:
    cfg = DaemonConfig(camera=CameraConfig(driver="sim", options={"fps": 30.0}), lamp=DeviceConfig(driver="sim"),
                       rangefinder=DeviceConfig(driver="sim-ping1d"),
                       simulation={"scene": "seabed-patch", "distance": 2.0, "size": list(size), "water": "jerlov-IB",
                                   "lamp_offset": [0.3, 0.0, 0.0], "material": "grey"},
                       recording=RecordingConfig(folder=os.path.dirname(path), budget_mb_s=None))  # every raw frame
    d = Daemon(cfg)
    d.start()
    try:
        while d.pipeline.processed < 3:
            time.sleep(0.1)
        d.recorder.start(path)
        while d.recorder.status()["frames_written"] < frames:
            time.sleep(0.1)
        d.recorder.stop()
    finally:
        d.stop()


def lengthen(src: str, dst: str, frames: int) -> int:
    """Repeat the recording's messages at later log times until ``frames`` ranged frames."""
    with open(src, "rb") as fh:
        reader = rec.open_reader(fh)
        msgs = [(c.topic, s.name, m.log_time, m.data) for s, c, m in reader.iter_messages()]
        atts = list(reader.iter_attachments())
    t0 = min(m[2] for m in msgs)
    span = max(m[2] for m in msgs) - t0 + 100_000_000
    per_copy = sum(1 for m in msgs if m[0] == rec.RANGING)
    out = rec.McapFile(dst)
    for a in atts:
        out.attach(a.name, a.media_type, a.data, a.log_time)
    copies = -(-frames // per_copy)
    for k in range(copies):
        for topic, schema, t, data in msgs:
            out.write(topic, "json" if schema == "uwcam.Json" else schema, data, t + k * span)
    out.finish()
    return copies * per_copy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="640x480", help="frame size WxH (default 640x480)")
    ap.add_argument("--frames", type=int, default=100, help="frames in the reprocessed dive (default 100)")
    ap.add_argument("--part-mb", type=float, default=32.0, help="megabytes per unit of work (default 32)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster (default 2)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        short, dive = os.path.join(tmp, "short.mcap"), os.path.join(tmp, "dive.mcap")
        record_dive(short, (w, h), min(args.frames, 20))
        n = lengthen(short, dive, args.frames)
        size_mb = os.path.getsize(dive) / 1e6
        assert ranged_frame_count(dive) == n
        print(f"dive: {n} frames of {w}x{h}x3 uint16, {size_mb:.0f} MB ({size_mb / n:.2f} MB/frame), "
              f"{len(plan(dive, args.part_mb))} parts of ~{args.part_mb:g} MB; CPU cores here: {os.cpu_count()}")

        # Warm both paths (imports, compiled kernels loaded from numba's cache): a campaign pays
        # this once per process, not per frame.
        first = plan(dive, args.part_mb)[0]
        process_part(first)
        t = time.perf_counter()
        reprocess([dive], os.path.join(tmp, "one.mcap"), progress=False, part_mb=args.part_mb)
        one = time.perf_counter() - t
        print(f"one process:             {n / one:7.1f} frames/s  ({one:.1f} s)")

        from distributed import Client, LocalCluster

        t = time.perf_counter()
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None) as c, \
                Client(c) as client:
            client.run(process_part, first, None, 1)
            startup = time.perf_counter() - t
            t = time.perf_counter()
            reprocess([dive], os.path.join(tmp, "dask.mcap"), progress=False, scheduler=c.scheduler_address,
                      part_mb=args.part_mb)
            dask = time.perf_counter() - t
            client.close()
        print(f"local cluster, {args.workers} workers: {n / dask:7.1f} frames/s  ({dask:.1f} s, "
              f"plus {startup:.1f} s cluster start-up and warm-up) = {one / dask:.2f}x one process")
        print(f"load average while measuring: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        out_mb = os.path.getsize(os.path.join(tmp, "one.mcap")) / 1e6 / n

    per_worker = n / dask / args.workers  # as measured here, on however many free cores there were
    dive_frames = 3600 * 10  # a one-hour dive at 10 frames/s
    print("\ncampaign of 50 one-hour dives at 10 frames/s "
          f"({50 * dive_frames:,} frames, {50 * dive_frames * size_mb / n / 1e6:.1f} TB raw), "
          f"at {per_worker:.1f} frames/s per worker as measured above:")
    for workers in (1, 16, 64, 256):
        rate = per_worker * workers
        print(f"  {workers:4d} workers: {50 * dive_frames / rate / 3600:8.1f} h  (~{rate:,.0f} frames/s, "
              f"results {rate * out_mb:,.0f} MB/s to the client)")
    print("Parts are independent (each reads its own MCAP chunks), so the work scales with workers until "
          "the shared storage's read rate (raw MB/frame × frames/s) or the client writing the results "
          "becomes the limit; at that point write results on the workers or run one client per dive.")


if __name__ == "__main__":
    main()
