"""Soak: the default simulated rig for a long while with everything a dive has going on at once.

The daemon (the embedded default rig, as ``uwcam run`` with no --config starts it, in a process
of its own) runs with:

* the operator page open in Debian's Chromium (Playwright, headless);
* a slow stream reader: a plain WebSocket client of ``/api/v1/stream`` that takes whatever
  there is every 2 s (the age of the newest range map it finds is recorded);
* a recording running from start to end (``recording.budget_mb_s`` set by --record-mb-s, so that
  a 30-minute soak fits the disk);
* the simulated lamp falling silent (hearing and answering nothing) for --silent-s in the
  middle of the run, then answering again.

Every --sample-s it samples the processed frame rate (processed frames over the interval), the
daemon's resident memory (RSS), the frames captured and dropped (status), the recorder's
counts, the lamp's health and the reader's newest map age, the frames the page painted, and
where the machine's CPU went (the daemon's CPU ms per processed frame, which includes the
simulated camera's rendering; the daemon's and Chromium's share of a core; the machine's idle
and stolen shares), and prints a row. At the end it stops
the recording, reads its files, and judges:

* fps: the processed rate over each whole cycle of the vehicle's altitude (120 s in the default
  rig; shorter windows measure how two cores share out their time among the loop, Chromium and
  the simulated camera: see ``scene_cycle_s``) within 10 % of the median of the cycles (the
  first, start-up, left out). Beside it, to tell a drift of the daemon from one of the machine,
  each cycle's rate scaled by how fast the machine's core ran in it (:class:`MachineProbe`: a
  fixed piece of work timed beside the daemon every 5 s);
* RSS: the peak of every interval (sampled each 0.5 s: the once-a-second ``malloc_trim`` hands
  memory back, so a single sample catches a phase of it) from --reference-minute on within 10 % of
  its value then (the minute is 5; in a run shorter than 10 minutes, the middle of the run);
* recording: every camera frame between the file's first and last is in the file (its metadata
  record, with or without its raw image), or counted as dropped by the camera in the status
  (camera.stats.dropped, part of frames.dropped; frames skipped for a newer one are recorded all
  the same) or lost by the recorder (recording.frames_lost);
* the lamp: shown not ok while silent and ok again after.

    python3 bench/soak.py [--minutes 30] [--sample-s 30] [--silent-s 60] [--record-mb-s 2] [--keep]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from tests.ports import free_port  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
STREAM_HEADER = struct.Struct("<4sIqqHHB3xf")  # docs/api.md: magic, frame, capture ns, send ns, w, h, dtype, scale


# ------------------------------------------------------------------------------------ the daemon

def serve(port: int, folder: str, record_mb_s: float) -> None:
    """The daemon process: the embedded default rig on ``port``, recordings into ``folder``. Reads
    commands on stdin: ``silent`` (the simulated lamp hears and says nothing), ``answer``."""
    import gc

    import uvicorn

    from uwcam.api import create_app
    from uwcam.config import default_config
    from uwcam.runtime.daemon import Daemon

    config = default_config()
    config.api.port = port
    config.recording.folder = folder
    config.recording.budget_mb_s = record_mb_s
    daemon = Daemon(config)
    app = create_app(config, daemon)
    daemon.start()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           ws_per_message_deflate=False))

    def commands() -> None:
        for line in sys.stdin:
            device = daemon.lamp.device
            if line.strip() == "silent":
                device.received = lambda data: None
            elif line.strip() == "answer":
                device.__dict__.pop("received", None)
            print(f"lamp {line.strip()}", flush=True)

    threading.Thread(target=commands, daemon=True).start()
    gc.freeze()  # as `uwcam run` does
    try:
        server.run()
    finally:
        daemon.stop()


def get(url: str, timeout: float = 10.0) -> dict:
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def post(url: str) -> dict:
    request = urllib.request.Request(url, data=b"", method="POST")
    with urllib.request.urlopen(request, timeout=30.0) as r:
        return json.loads(r.read())


def cpu_s(pids: list[int]) -> float:
    """CPU seconds (user + system) the processes ``pids`` have used so far (gone ones count 0)."""
    total = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of proc(5))
    return total / os.sysconf("SC_CLK_TCK")


def chromium_pids() -> list[int]:
    """Every process of Debian's Chromium (the page's browser, its renderer and GPU processes)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as fh:
                    if b"chromium" in fh.read().split(b"\0", 1)[0]:
                        pids.append(int(entry))
            except OSError:
                pass
    return pids


def machine_times() -> tuple[float, float, float]:
    """The machine's CPU seconds so far, summed over its cores: busy, idle, stolen (by the
    hypervisor for other guests: time this machine wanted and did not get)."""
    with open("/proc/stat") as fh:
        user, nice, system, idle, iowait, irq, softirq, steal = (int(v) for v in fh.readline().split()[1:9])
    tick = os.sysconf("SC_CLK_TCK")
    return (user + nice + system + irq + softirq) / tick, (idle + iowait) / tick, steal / tick


class MachineProbe:
    """The machine's speed, measured beside the daemon: the CPU time (this thread's, so not how
    the cores are shared out) of a fixed piece of work like the frame loop's (logarithms and
    products over a 720p float32 frame). A virtual machine's core gets faster or slower as the
    host's other guests come and go; the daemon's frame rate moves with it, and this is the
    baseline measured in the same run that tells the two apart."""

    def __init__(self) -> None:
        import numpy as np

        self._np = np
        self._frame = np.random.default_rng(0).uniform(1.0, 4000.0, (720, 1280, 3)).astype(np.float32)
        self._out = np.empty_like(self._frame)
        self.samples_ms: list[float] = []

    def measure(self) -> None:
        t = time.thread_time()
        self._np.log(self._frame, out=self._out)
        self._np.multiply(self._out, self._frame, out=self._out)
        float(self._out.sum())
        self.samples_ms.append((time.thread_time() - t) * 1e3)

    def take(self) -> float:
        """The median CPU ms of the measurements since the last take (NaN: none)."""
        samples, self.samples_ms = self.samples_ms, []
        return statistics.median(samples) if samples else float("nan")


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


# ------------------------------------------------------------------------------------ the clients

class SlowReader(threading.Thread):
    """A plain WebSocket client of /api/v1/stream that takes what there is every ``every_s``."""

    def __init__(self, port: int, every_s: float = 2.0) -> None:
        super().__init__(daemon=True)
        self.port, self.every_s = port, every_s
        self.ages: list[float] = []  # newest map's age (s) at each read; inf: none there
        self.stop = threading.Event()
        self.error: str | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._read())
        except Exception as exc:  # noqa: BLE001 (reported in the verdict)
            self.error = repr(exc)

    async def _read(self) -> None:
        import websockets

        async with websockets.connect(f"ws://127.0.0.1:{self.port}/api/v1/stream", max_size=None) as ws:
            await asyncio.wait_for(ws.recv(), 30.0)  # hello
            while not self.stop.is_set():
                await asyncio.sleep(self.every_s)
                newest = None
                while True:
                    try:
                        msg = await asyncio.wait_for(ws.recv(), 0.005)
                    except TimeoutError:
                        break
                    if isinstance(msg, bytes):
                        newest = STREAM_HEADER.unpack_from(msg)[2]
                self.ages.append(float("inf") if newest is None else (time.time_ns() - newest) / 1e9)


def recorded_sequences(paths: list[str]) -> list[int]:
    """Camera sequence numbers of every frame recorded (metadata record, raw image or not)."""
    from uwcam.recording import format as rec

    sequences = []
    for path in paths:
        with open(path, "rb") as fh:
            reader = rec.open_reader(fh)
            for _, _, _, decoded in reader.iter_decoded_messages(topics=[rec.IMAGE_METADATA]):
                sequences.append(int(decoded["sequence"]))
    return sequences


# ------------------------------------------------------------------------------------ the soak

def soak(args: argparse.Namespace) -> int:
    from playwright.sync_api import sync_playwright

    folder = tempfile.mkdtemp(prefix="uwcam-soak-")
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    daemon = subprocess.Popen([sys.executable, __file__, "--serve", str(port), folder, str(args.record_mb_s)],
                              stdin=subprocess.PIPE, text=True)
    verdicts: list[tuple[str, bool, str]] = []
    try:
        deadline = time.monotonic() + 300.0
        while True:  # calibration in simulated water and numba's compilation come first
            try:
                if get(f"{base}/api/v1/status", 2.0)["frames"]["processed"] > 0:
                    break
            except (OSError, ValueError, KeyError):
                pass
            if daemon.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("the daemon did not start ranging")
            time.sleep(1.0)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page_errors: list[str] = []
            page.on("pageerror", lambda e: page_errors.append(str(e)))
            page.goto(f"{base}/")
            reader = SlowReader(port)
            reader.start()
            before = get(f"{base}/api/v1/status")
            started = post(f"{base}/api/v1/recordings/start")
            print(f"daemon pid {daemon.pid} on {base}; recording {started.get('file')}; "
                  f"{args.minutes:g} min, a sample every {args.sample_s:g} s", flush=True)
            rows = run_samples(args, base, daemon, page, reader)
            stopped = post(f"{base}/api/v1/recordings/stop")
            after = get(f"{base}/api/v1/status")
            reader.stop.set()
            reader.join(10.0)
            browser.close()
        recording = get(f"{base}/api/v1/recordings/status")
        files = [f if os.path.isabs(f) else os.path.join(folder, f) for f in (stopped.get("files") or recording["files"])]
        dropped = after["frames"]["dropped"] - before["frames"]["dropped"]
        by_camera = after["camera"]["stats"].get("dropped", 0) - before["camera"]["stats"].get("dropped", 0)
        verdicts += judge(args, rows, files, recording, (dropped, by_camera), reader, page_errors)
    finally:
        daemon.terminate()
        try:
            daemon.wait(60.0)
        except subprocess.TimeoutExpired:
            daemon.kill()
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    print()
    for name, ok, detail in verdicts:
        print(f"{'PASS' if ok else 'FAIL'}  {name}: {detail}")
    passed = all(ok for _, ok, _ in verdicts)
    print("soak", "passed" if passed else "FAILED")
    return 0 if passed else 1


def run_samples(args, base: str, daemon: subprocess.Popen, page, reader: SlowReader) -> list[dict]:
    total_s = args.minutes * 60.0
    silent_from = total_s / 2 - args.silent_s / 2
    silent_until = silent_from + args.silent_s
    start = time.monotonic()
    status = get(f"{base}/api/v1/status")
    last = (start, status["frames"]["processed"])
    rows: list[dict] = []
    lamp_phase = "before"
    probe = MachineProbe()
    probe_every_s, next_probe = 5.0, start
    cpu = (cpu_s([daemon.pid]), cpu_s(chromium_pids()), *machine_times())
    painted = page.evaluate("window.uwcam.stats.displayed")
    print(f"{'t_min':>6} {'fps':>6} {'rss_MB':>7} {'captured':>9} {'dropped':>8} {'rec_written':>11} "
          f"{'rec_dropped':>11} {'rec_lost':>8} {'lamp':>22} {'reader_age_s':>12} {'latency_ms':>10} {'page':>5} "
          f"{'painted':>7} {'rf_m':>5} {'cpu_ms/frame':>12} {'daemon%':>7} {'chromium%':>9} {'idle%':>5} {'steal%':>6} {'probe_ms':>8}", flush=True)
    while len(rows) * args.sample_s + args.sample_s <= total_s + 0.01:
        next_sample = start + (len(rows) + 1) * args.sample_s
        peak_rss = 0.0
        while time.monotonic() < next_sample:
            now = time.monotonic() - start
            if lamp_phase == "before" and now >= silent_from:
                daemon.stdin.write("silent\n")
                daemon.stdin.flush()
                lamp_phase = "silent"
            elif lamp_phase == "silent" and now >= silent_until:
                daemon.stdin.write("answer\n")
                daemon.stdin.flush()
                lamp_phase = "after"
            peak_rss = max(peak_rss, rss_mb(daemon.pid))  # the interval's peak: growth, not malloc_trim's phase
            if time.monotonic() >= next_probe:
                probe.measure()
                next_probe += probe_every_s
            time.sleep(min(0.5, max(0.0, next_sample - time.monotonic())))
        status = get(f"{base}/api/v1/status")
        t = time.monotonic()
        processed = status["frames"]["processed"]
        ages = reader.ages[len(sum((r["ages"] for r in rows), [])):]
        page_alive = page.evaluate("document.readyState") == "complete"
        lamp = status["lamp"]["health"] if status.get("lamp") else {"state": "none", "reason": ""}
        latency = status.get("latency_ms")  # capture → processed, as the daemon measures it
        latency = "/".join(f"{latency[k]:.0f}" for k in ("p50", "p99") if k in latency) if isinstance(latency, dict) else str(latency)
        now_cpu = (cpu_s([daemon.pid]), cpu_s(chromium_pids()), *machine_times())
        used = [b - a for a, b in zip(cpu, now_cpu)]
        cpu = now_cpu
        wall = t - last[0]
        now_painted = page.evaluate("window.uwcam.stats.displayed")
        row = {"t_s": t - start, "processed": processed, "fps": (processed - last[1]) / wall, "rss_mb": max(peak_rss, rss_mb(daemon.pid)),
               "painted_fps": (now_painted - painted) / wall,
               "rf_m": ((status.get("rangefinder") or {}).get("range_m") or float("nan")),
               "daemon_ms_per_frame": 1e3 * used[0] / max(processed - last[1], 1),
               "daemon_pct": 100 * used[0] / wall, "chromium_pct": 100 * used[1] / wall,
               "idle_pct": 100 * used[3] / max(used[2] + used[3] + used[4], 1e-9),
               "steal_pct": 100 * used[4] / max(used[2] + used[3] + used[4], 1e-9),
               "probe_ms": probe.take(),
               "captured": status["frames"]["captured"], "dropped": status["frames"]["dropped"],
               "recording": status["recording"], "lamp_state": lamp["state"], "lamp_reason": lamp.get("reason", ""),
               "lamp_phase": lamp_phase, "ages": ages, "page": page_alive}
        last = (t, processed)
        painted = now_painted
        rows.append(row)
        rec = row["recording"] or {}
        print(f"{row['t_s'] / 60:6.2f} {row['fps']:6.1f} {row['rss_mb']:7.0f} {row['captured']:9d} {row['dropped']:8d} "
              f"{rec.get('frames_written', 0):11d} {rec.get('frames_dropped', 0):11d} {rec.get('frames_lost', 0):8d} "
              f"{(lamp['state'] + '/' + lamp_phase)[:22]:>22} {max(ages, default=float('nan')):12.2f} "
              f"{latency:>10} "
              f"{'ok' if page_alive else 'gone':>5} {row['painted_fps']:7.1f} {row['rf_m']:5.2f} {row['daemon_ms_per_frame']:12.0f} "
              f"{row['daemon_pct']:7.0f} {row['chromium_pct']:9.0f} {row['idle_pct']:5.0f} {row['steal_pct']:6.1f} {row['probe_ms']:8.1f}", flush=True)
    return rows


def scene_cycle_s() -> float:
    """Seconds after which the default rig's vehicle repeats its altitude: windows of whole cycles
    each hold the same ranges. (A 5-minute run with 10-s samples: the rate did not follow the
    altitude, correlation 0.14; the 10-s rates spread over 7.4-9.2 fps, the 30-s ones of a 10-minute
    run over 8.2-9.9: the two cores' scheduling between the loop, Chromium and the simulated camera.
    A window of a cycle averages that jitter out and still shows a trend within a few minutes.)"""
    from uwcam.config import default_config

    return float(default_config().simulation["altitude_period"])


def cycle_windows(rows: list[dict], cycle_s: float) -> list[tuple[float, list[dict]]]:
    """(processed frames per second, the samples) in consecutive windows of ``cycle_s`` (each
    ending at the sample at or just after its end; a trailing partial window is left out)."""
    windows, start_t, start_n = [], 0.0, rows[0]["processed"] - rows[0]["fps"] * rows[0]["t_s"]
    held: list[dict] = []
    for row in rows:
        held.append(row)
        if row["t_s"] >= start_t + cycle_s - 1.0:
            windows.append(((row["processed"] - start_n) / (row["t_s"] - start_t), held))
            start_t, start_n, held = row["t_s"], row["processed"], []
    return windows


def window_probes(windows: list[tuple[float, list[dict]]]) -> list[float]:
    """Each window's median probe CPU ms (:class:`MachineProbe`)."""
    return [statistics.median(r["probe_ms"] for r in held) for _, held in windows]


def machine_normalised(windows: list[tuple[float, list[dict]]]) -> list[float]:
    """Each window's rate on a machine of constant speed: times the window's probe CPU ms over the
    median probe of all windows (a window whose core ran 10 % faster counts 10 % fewer frames)."""
    probes = window_probes(windows)
    reference = statistics.median(probes)
    return [rate * probe / reference for (rate, _), probe in zip(windows, probes)]


def judge(args, rows: list[dict], files: list[str], recording: dict, dropped: tuple[int, int], reader: SlowReader,
          page_errors: list[str]) -> list[tuple[str, bool, str]]:
    verdicts = []
    cycle_s = scene_cycle_s()
    windows = cycle_windows(rows, cycle_s)[1:]  # the first cycle holds the start-up
    if len(windows) >= 2:
        raw = [rate for rate, _ in windows]
        steady = machine_normalised(windows)
        probes = window_probes(windows)

        def spread(rates: list[float]) -> tuple[float, float]:
            median = statistics.median(rates)
            return median, max(abs(f / median - 1.0) for f in rates)

        (raw_median, raw_worst), (median, worst) = spread(raw), spread(steady)
        samples = [r["fps"] for r in rows[1:]]
        verdicts.append(("fps within 10 %", raw_worst <= 0.10,
                         f"median {raw_median:.2f} fps over {len(windows)} windows of one scene cycle ({cycle_s:g} s): "
                         f"{', '.join(f'{f:.2f}' for f in raw)} (worst {raw_worst * 100:.1f} % off); the "
                         f"{args.sample_s:g}-s samples {min(samples):.1f}-{max(samples):.1f}. For a drift, the machine: "
                         f"its probe's fixed work took {', '.join(f'{p:.1f}' for p in probes)} CPU ms, and on a machine "
                         f"of constant speed the cycles would be {', '.join(f'{f:.2f}' for f in steady)} "
                         f"(median {median:.2f}, worst {worst * 100:.1f} % off)"))
    else:
        verdicts.append(("fps within 10 %", False, f"the run holds fewer than 3 scene cycles of {cycle_s:g} s: run longer"))
    total_min = args.minutes
    reference_min = args.reference_minute if total_min >= 2 * args.reference_minute else total_min / 2
    reference = next(r for r in rows if r["t_s"] >= reference_min * 60.0 - 1.0)
    later = [r for r in rows if r["t_s"] >= reference["t_s"]]
    drift = max(abs(r["rss_mb"] / reference["rss_mb"] - 1.0) for r in later)
    verdicts.append((f"RSS within 10 % of its value at minute {reference['t_s'] / 60:.1f}", drift <= 0.10,
                     f"{reference['rss_mb']:.0f} MB then; {min(r['rss_mb'] for r in later):.0f}-"
                     f"{max(r['rss_mb'] for r in later):.0f} MB after (worst {drift * 100:.1f} % off); median of the "
                     f"last quarter {statistics.median(r['rss_mb'] for r in rows[-max(1, len(rows) // 4):]):.0f} MB; "
                     f"first sample {rows[0]['rss_mb']:.0f} MB"))
    sequences = recorded_sequences(files)
    unique = sorted(set(sequences))
    span = unique[-1] - unique[0] + 1 if unique else 0
    missing = span - len(unique)
    lost = recording.get("frames_lost", 0)
    dropped, by_camera = dropped  # status frames.dropped during the recording; of them, the camera's own
    duplicates = len(sequences) - len(unique)
    # Frames skipped for a newer one are recorded all the same (unranged): only the camera's own
    # drops (never delivered) and the recorder's losses may leave gaps.
    verdicts.append(("no recorded frame lost unaccounted", bool(unique) and missing <= by_camera + lost and duplicates == 0,
                     f"{len(unique)} frames recorded in {len(files)} file(s), sequences {unique[0] if unique else '-'}"
                     f"-{unique[-1] if unique else '-'}: {missing} missing; status counted {dropped} dropped during the "
                     f"recording ({by_camera} by the camera, the rest skipped for a newer frame) + {lost} lost by the recorder; {recording.get('frames_dropped', 0)} raw images shed and "
                     f"{recording.get('frames_decimated', 0)} decimated (their metadata kept); {duplicates} duplicates"))
    silent = [r for r in rows if r["lamp_phase"] == "silent"]
    after = [r for r in rows if r["lamp_phase"] == "after"]
    shown = any(r["lamp_state"] != "ok" for r in silent) and bool(after) and after[-1]["lamp_state"] == "ok"
    verdicts.append(("silent lamp shown, then answering", shown,
                     f"while silent: {sorted({r['lamp_state'] + ' (' + r['lamp_reason'] + ')' for r in silent})}; "
                     f"at the end: {after[-1]['lamp_state'] if after else '-'}"))
    ages = [a for r in rows[2:] for a in r["ages"]]  # the reader's first reads teach the daemon its pace
    verdicts.append(("slow reader's newest map at most 1.5 s old", bool(ages) and max(ages) <= 1.5 and reader.error is None,
                     f"{len(ages)} reads, median {statistics.median(ages) if ages else float('nan'):.2f} s, "
                     f"max {max(ages, default=float('nan')):.2f} s{'; ' + reader.error if reader.error else ''}"))
    verdicts.append(("page open throughout", all(r["page"] for r in rows) and not page_errors,
                     f"{len(page_errors)} page errors{': ' + page_errors[0][:120] if page_errors else ''}"))
    return verdicts


def main() -> int:
    if len(sys.argv) == 5 and sys.argv[1] == "--serve":
        serve(int(sys.argv[2]), sys.argv[3], float(sys.argv[4]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="duration of the soak (default 30)")
    parser.add_argument("--sample-s", type=float, default=30.0, help="seconds between samples (default 30)")
    parser.add_argument("--silent-s", type=float, default=60.0, help="seconds the lamp is silent, mid-run (default 60)")
    parser.add_argument("--record-mb-s", type=float, default=2.0, help="recording.budget_mb_s (default 2)")
    parser.add_argument("--reference-minute", type=float, default=5.0, help="RSS reference (default minute 5)")
    parser.add_argument("--keep", action="store_true", help="keep the recording (its folder is printed)")
    args = parser.parse_args()
    if not (args.minutes > 0 and args.sample_s > 0 and 0 < args.silent_s < args.minutes * 60 and args.record_mb_s > 0):
        parser.error("--minutes, --sample-s, --record-mb-s must be > 0 and --silent-s within the run")
    if args.minutes * 60 < 3 * args.sample_s:
        parser.error("the run must hold at least three samples: lower --sample-s")
    return soak(args)


if __name__ == "__main__":
    sys.exit(main())
