"""Benchmark: the whole daemon (`uwcam run`, its own process) with one WebSocket client.

Two rigs:
* replay — a real-rig configuration: the `replay` camera driver playing 1920×1080 three-channel
  16-bit frames (.npy, written here: a seabed sloping from 1 m to 8 m with camera noise) at
  --fps (default 60), a calibration profile file, no simulated devices;
* sim — the embedded default (no --config): simulated camera, lamp and Ping1D, calibrated in
  simulated water at start.

For each: time from process start to the first answered status and to the first range (first
processed frame), frames captured and dropped and the latency p99 in the first 20 s (start-up),
then over --seconds more: processed fps, drops (queue overflow or skipped for a newer frame),
latency from capture to WebSocket send (from the stream's own header), daemon CPU and resident
memory (RSS, sampled every second; the peak is printed).

    python3 bench/bench_daemon.py [--seconds 30] [--fps 60] [--rigs replay,sim,sim-backscatter] [--frames 8] [--startup-seconds 20]
                                  [--record FOLDER [--record-results] [--budget MB_S] [--compression lz4|zstd|none]]

--record FOLDER: the replay rig records the whole run into FOLDER (MCAP, every topic) as
`uwcam run --record` does; the recorder's own figures (frames written and dropped, MB written)
are printed. Give a folder on the disk the vehicle would record to (a tmpfs measures the CPU
cost alone); it must have room for the run. By default the recording holds the raw frames and
what `uwcam reprocess` needs to range them again (recording.results: false); --record-results
adds the results. --budget sets recording.budget_mb_s (0: no budget; default the
configuration's, 40 MB/s): the MB/s written and the share of raw frames kept are printed.
--compression sets recording.compression.

sim-backscatter: the embedded default with backscatter compensation switched on through the API
as soon as the daemon answers; with "sim" in the same run, the ratio of the two is printed.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np
import websockets

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from tests.ports import free_port

# The stream's header as docs/api.md gives it. The measuring process imports nothing of uwcam's
# (the rig is written by a child process): a process here that loaded numba would share the
# compiler library's pages with the daemon, which then cannot drop them (madvise MADV_PAGEOUT
# leaves shared pages alone) and would show ~40 MB more resident memory than it has alone.
HEADER = struct.Struct("<4sIqqHHB3xf")

STARTUP_S = 20.0  # the start-up window, changed by --startup-seconds


def proc_figures(pid: int) -> tuple[float, float, float]:
    """(CPU seconds used, resident MB, of which anonymous MB) of a process, from /proc. The rest of
    resident memory is file-backed: shared-library code, reclaimable under memory pressure."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    with open(f"/proc/{pid}/status") as fh:
        kb = {line.split(":")[0]: int(line.split()[1]) for line in fh if line.startswith(("VmRSS:", "RssAnon:"))}
    return cpu, kb["VmRSS"] / 1024.0, kb["RssAnon"] / 1024.0


def write_replay_rig(folder: str, size: tuple[int, int], fps: float, frames: int, port: int,
                     recording: dict | None = None) -> str:
    """Frames, a matching calibration profile and a configuration for the replay camera; returns the config path."""
    import yaml

    from tests.synthetic import make_profile
    from uwcam.calibration.profile import save_profile

    w, h = size
    attenuation = np.array([0.46, 0.11, 0.06])
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w]
    path = 1.0 + 7.0 * (1.0 - yy / h) ** 2 + 0.3 * np.sin(xx / 37.0) * np.cos(yy / 23.0)
    clean = 6e4 * np.exp(-attenuation * path[..., None])
    os.makedirs(os.path.join(folder, "frames"))
    for i in range(frames):
        noisy = clean + np.sqrt(25.0 + 0.3 * clean) * rng.standard_normal(clean.shape)
        np.save(os.path.join(folder, "frames", f"{i:04d}.npy"), np.clip(noisy, 0, 65535).astype(np.uint16))
    profile = make_profile(attenuation, [0.0, 0.0, 0.0], read_noise=5.0, shot_gain=0.3, noise_floor=30.0)
    save_profile(profile, os.path.join(folder, "profile.yaml"))
    cfg = os.path.join(folder, "rig.yaml")
    with open(cfg, "w") as fh:
        yaml.safe_dump({
            "version": 1,
            "camera": {"driver": "replay", "options": {"source": os.path.join(folder, "frames"), "fps": float(fps)}},
            "calibration": os.path.join(folder, "profile.yaml"),
            "api": {"host": "127.0.0.1", "port": port, "stream_rate_hz": 120.0},
            **({"recording": recording} if recording else {}),
        }, fh)
    return cfg


def measure(args: list[str], port: int, seconds: float, settings: dict | None = None) -> dict:  # noqa: C901
    """Start `uwcam run ARGS`, stream from it from the first moment it answers, and measure it;
    ``settings``: processing settings PATCHed as soon as it answers (before the start-up window ends)."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "uwcam", "run", *args, "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    status_url = f"http://127.0.0.1:{port}/api/v1/status"

    def status() -> dict:
        return json.load(urllib.request.urlopen(status_url, timeout=10))

    try:
        while True:
            try:
                status()
                break
            except OSError:
                if time.monotonic() - t0 > 180 or proc.poll() is not None:
                    raise RuntimeError(f"uwcam run did not start: {proc.stderr.read().decode()[-2000:]}") from None
                time.sleep(0.05)
        t_status = time.monotonic() - t0
        if settings:
            request = urllib.request.Request(f"http://127.0.0.1:{port}/api/v1/config", data=json.dumps(settings).encode(),
                                             method="PATCH", headers={"Content-Type": "application/json"})
            urllib.request.urlopen(request, timeout=30).read()
        rss, frames_at = [], {}

        async def client() -> tuple[list, float | None, float]:
            received = []  # (seconds since start, latency ms)
            first_range = None
            cpu_at_startup_end = 0.0
            async with websockets.connect(f"ws://127.0.0.1:{port}/api/v1/stream?rate=120", max_size=None) as ws:
                await ws.recv()  # hello
                next_sample = 0.0
                # Measured for `seconds` after the start-up snapshot, however late a loaded machine
                # lets the daemon start (its first status can come after STARTUP_S).
                while "startup" not in frames_at or (now := time.monotonic() - t0) < frames_at["t_startup"] - t0 + seconds:
                    now = time.monotonic() - t0
                    if now >= next_sample:
                        rss.append(proc_figures(proc.pid)[1:])
                        next_sample += 1.0
                    if "startup" not in frames_at and now >= STARTUP_S:
                        frames_at["startup"] = (await asyncio.to_thread(status))["frames"]
                        frames_at["t_startup"] = time.monotonic()
                        cpu_at_startup_end = proc_figures(proc.pid)[0]
                    try:
                        msg = await asyncio.wait_for(ws.recv(), timeout=0.5)
                    except TimeoutError:
                        continue
                    if isinstance(msg, bytes):
                        _, _, captured, sent, *_ = HEADER.unpack_from(msg)
                        if first_range is None:
                            first_range = time.monotonic() - t0
                        received.append((time.monotonic() - t0, (sent - captured) / 1e6))
                final = await asyncio.to_thread(status)
                frames_at["end"] = final["frames"]
                frames_at["recording"] = final.get("recording")
                frames_at["t_end"] = time.monotonic()
                return received, first_range, proc_figures(proc.pid)[0] - cpu_at_startup_end

        received, t_first_range, cpu = asyncio.run(client())
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    start, end = frames_at["startup"], frames_at["end"]
    span = frames_at["t_end"] - frames_at["t_startup"]  # between the two status snapshots
    early = [lat for t, lat in received if t < STARTUP_S]
    late = [lat for t, lat in received if t >= STARTUP_S]
    processed = end["processed"] - start["processed"]
    return {
        "first_status_s": t_status, "first_range_s": t_first_range,
        "startup": {"captured": start["captured"], "dropped": start["dropped"],
                    "p99_ms": float(np.percentile(early, 99)) if early else float("nan")},
        "fps": processed / span, "captured": end["captured"] - start["captured"], "processed": processed,
        "dropped": end["dropped"] - start["dropped"], "sent": len(late),
        "p50_ms": float(np.percentile(late, 50)) if late else float("nan"),
        "p99_ms": float(np.percentile(late, 99)) if late else float("nan"),
        "cpu_percent": 100.0 * cpu / span, "cpu_ms_per_frame": 1e3 * cpu / max(processed, 1), "rss_peak_mb": max(r for r, _ in rss), "rss_end_mb": rss[-1][0],
        "anon_peak_mb": max(a for _, a in rss), "anon_end_mb": rss[-1][1],
        "recording": frames_at.get("recording"),
    }


def report(name: str, r: dict, seconds: float, fps: float | None) -> None:
    print(f"{name}:")
    print(f"  start-up: first status {r['first_status_s']:.2f} s, first range {r['first_range_s']:.2f} s after process start"
          f" (goal < 3 s: {'met' if r['first_range_s'] is not None and r['first_range_s'] < 3 else 'NOT met'}); first "
          f"{STARTUP_S:g} s: {r['startup']['dropped']} of {r['startup']['captured']} frames dropped, "
          f"p99 {r['startup']['p99_ms']:.0f} ms")
    goal = ""
    if fps is not None:
        ok = r["dropped"] == 0 and r["p99_ms"] < 50 and r["fps"] >= 0.98 * fps
        goal = f" (goal {fps:g} fps, no drops, p99 < 50 ms: {'met' if ok else 'NOT met'})"
    print(f"  next {seconds:g} s: processed {r['fps']:.1f} fps ({r['processed']} of {r['captured']} captured), "
          f"dropped {r['dropped']}, sent to the client {r['sent']}; latency capture → send p50 {r['p50_ms']:.1f} ms, "
          f"p99 {r['p99_ms']:.1f} ms{goal}")
    print(f"  daemon CPU {r['cpu_percent']:.0f} % of one core, {r['cpu_ms_per_frame']:.1f} ms per processed frame (less disturbed by "
          f"other load than the rates); resident memory peak {r['rss_peak_mb']:.0f} MB, "
          f"at the end {r['rss_end_mb']:.0f} MB (goal < 250 MB on a real rig); anonymous (not shared-library "
          f"code) peak {r['anon_peak_mb']:.0f} MB, at the end {r['anon_end_mb']:.0f} MB")
    rec = r.get("recording")
    if rec and rec.get("state") != "idle" or rec and rec.get("frames_written"):
        print(f"  recording ({rec['state']}): {rec['frames_written']} frames written, {rec['frames_dropped']} dropped by the "
              f"recorder (the disk or its share of the CPU could not keep up), "
              f"{rec['bytes'] / 1e6:.0f} MB, {rec['queued']} queued at the end")
        if rec.get("duration_s"):
            print(f"  recording rate {rec['bytes'] / 1e6 / rec['duration_s']:.1f} MB/s over {rec['duration_s']:.0f} s "
                  f"(budget {rec.get('budget_mb_s')} MB/s); raw frames kept {100 * (rec.get('raw_kept_ratio') or 0):.0f} % "
                  f"({rec.get('frames_decimated', 0)} decimated); {rec.get('hours_left')} h of disk left at that budget")


def main() -> None:
    if sys.argv[1:2] == ["--write-rig"]:
        write_replay_rig(*json.loads(sys.argv[2]))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="measured after the 20 s start-up window")
    parser.add_argument("--fps", type=float, default=60.0, help="replay frame rate")
    parser.add_argument("--size", default="1920x1080", help="replayed frame size WxH")
    parser.add_argument("--frames", type=int, default=8, help="distinct replayed frames (looped)")
    parser.add_argument("--rigs", default="replay,sim", help="which rigs to run, comma-separated")
    parser.add_argument("--startup-seconds", type=float, default=20.0, help="start-up window")
    parser.add_argument("--record", metavar="FOLDER", help="the replay rig records into this folder (MCAP)")
    parser.add_argument("--record-raw-only", action="store_true", help="record without the results (the default now)")
    parser.add_argument("--record-results", action="store_true", help="record the results too (recording.results: true)")
    parser.add_argument("--budget", type=float, help="recording.budget_mb_s (0: none)")
    parser.add_argument("--compression", choices=("lz4", "zstd", "none"), help="recording.compression")
    args = parser.parse_args()
    global STARTUP_S
    STARTUP_S = args.startup_seconds
    w, h = (int(v) for v in args.size.split("x"))
    print(f"uwcam daemon with one WebSocket client; {os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f}")
    rigs = args.rigs.split(",")
    if "replay" in rigs:
        with tempfile.TemporaryDirectory() as tmp:
            port = free_port()
            recording = {"results": bool(args.record_results),
                         **({"budget_mb_s": args.budget or None} if args.budget is not None else {}),
                         **({"compression": args.compression} if args.compression else {})}
            # In a child process: see HEADER above.
            subprocess.run([sys.executable, __file__, "--write-rig", json.dumps(
                [tmp, [w, h], args.fps, args.frames, port, recording])], check=True)
            cfg = os.path.join(tmp, "rig.yaml")
            record = []
            if args.record:
                record = ["--record", os.path.join(os.path.abspath(args.record), f"bench-{time.strftime('%Y%m%dT%H%M%S')}.mcap")]
            r = measure(["--config", cfg, *record], port, args.seconds)
        report(f"replay {w}x{h}x3 uint16 at {args.fps:g} fps (a real-rig configuration"
               f"{', recording' if record else ''}{' with results' if args.record_results else ''}"
               f"{', ' + args.compression if record and args.compression else ''})", r, args.seconds, args.fps)
    sim = {}
    if "sim" in rigs:
        port = free_port()
        sim["off"] = r = measure([], port, args.seconds)
        report("embedded default (simulated camera, lamp and Ping1D)", r, args.seconds, None)
    if "sim-backscatter" in rigs:
        port = free_port()
        sim["on"] = r = measure([], port, args.seconds, settings={"backscatter": {"iterations": 2}})
        report("embedded default with backscatter compensation (2 iterations)", r, args.seconds, None)
    if len(sim) == 2:
        print(f"backscatter compensation on / off, same machine, one after the other: processed fps "
              f"{sim['on']['fps'] / sim['off']['fps']:.2f}×, CPU per frame "
              f"{sim['on']['cpu_ms_per_frame'] / sim['off']['cpu_ms_per_frame']:.2f}×, drops {sim['off']['dropped']} → "
              f"{sim['on']['dropped']}, p99 {sim['off']['p99_ms']:.0f} → {sim['on']['p99_ms']:.0f} ms")


if __name__ == "__main__":
    main()
