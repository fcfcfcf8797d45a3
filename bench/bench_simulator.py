"""Benchmark: simulator speed.

Prints (1) the time to render a new 640×480 three-channel scene with 32 backscatter slabs
(goal ≤ 1 s), split into ray casting and image formation, (2) the rate at which a
static 1280×720 three-channel scene delivers new noisy 16-bit frames (goal ≥ 30 fps),
beside numpy drawing the same number of normal deviates in the same run, and (3) frames/s
of the simulated camera's frame path on one thread (numba threads = 1, as the driver runs)
at 1280×720 and 1920×1080 for a static scene and for the survey (a new view every frame:
geometry and light in ms, then exposure and noise in ms; goal: 1080p at ≥ 30 fps, a 720p
survey render ≤ 15 ms), with a memory copy of the frame as the same-run yardstick.

    python3 bench/bench_simulator.py [--repeat N] [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from timing import best_time  # noqa: E402
from uwcam.simulation import Lamp, SimulatedWorld, water_preset  # noqa: E402
from uwcam.compute.jit import HAVE_NUMBA, set_threads  # noqa: E402
from uwcam.simulation.survey import SurveyWorld  # noqa: E402
from uwcam.simulation.survey_kernels import upsample  # noqa: E402


def cpu_time(fn, repeat: int) -> tuple[float, float]:
    """(best, median) CPU time of this thread per call, s: on a machine shared with other load
    it measures the work itself, where wall time also counts waiting for a core."""
    times = []
    for _ in range(repeat):
        t = time.thread_time()
        fn()
        times.append(time.thread_time() - t)
    return min(times), float(np.median(times))


def camera_path(repeat: int, sizes: list[tuple[int, int]]) -> None:
    """Frames/s of the simulated camera's frame path, one thread, static scene and survey."""
    set_threads(1)
    water = water_preset("jerlov-IA", [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.3, -0.8, 0.0))
    print(f"simulated camera frame path, one thread (numba {'on' if HAVE_NUMBA else 'missing: numpy twins'}); "
          "CPU ms of this thread per frame (median), frames/s = 1000 / that; wall-clock median in brackets:")
    for w, h in sizes:
        out = np.empty((h, w, 3), np.uint16)
        copy_src = np.empty_like(out)
        static = SimulatedWorld(scene="seabed-patch", distance=2.0, size=(w, h), water=water, lamp=lamp)
        static.frame(0, out=out)
        index = iter(range(1, 10**6))
        survey = SurveyWorld(size=(w, h), water=water, lamp=lamp)
        survey.frame(0.0, 0, out=out)
        clock = iter(np.arange(1.0, 10**6, 1 / 30))
        lamp_rad = survey.shade(5.0)[0]
        rows = {
            "copy": (lambda: np.copyto(out, copy_src)),
            "static": (lambda: static.frame(next(index), out=out)),
            "render": (lambda: survey.shade(next(clock))),
            "interpolation": (lambda: upsample(lamp_rad, (w, h), survey.step)),
            "survey": (lambda: survey.frame(next(clock), 1, out=out)),
        }
        cpu = {k: cpu_time(f, repeat)[1] * 1e3 for k, f in rows.items()}
        wall = {k: best_time(f, repeat)[1] * 1e3 for k, f in rows.items()}
        for name, label in (("static", "static scene (seabed-patch)"), ("survey", "survey, a new view per frame")):
            goal = "met" if 1e3 / cpu[name] >= 30 else "NOT met"
            print(f"  {w}x{h} {label:30s} {cpu[name]:6.1f} ms = {1e3 / cpu[name]:5.0f} fps [wall {wall[name]:6.1f} ms]; "
                  f"≥ 30 fps on one core: {goal}")
        print(f"  {w}x{h} survey parts: render (geometry + light, {survey.grid_size[0]}x{survey.grid_size[1]} points) "
              f"{cpu['render']:.1f} ms [wall {wall['render']:.1f}], interpolation {cpu['interpolation']:.1f} ms, "
              f"exposure + noise {cpu['survey'] - cpu['render'] - cpu['interpolation']:.1f} ms; "
              f"memory copy of the frame {cpu['copy']:.2f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="only the simulated camera's frame path")
    args = parser.parse_args()
    camera_path(args.repeat * 4, [(1280, 720), (1920, 1080)])
    if args.quick:
        return
    water = water_preset("jerlov-II", [675.0, 575.0, 475.0])
    lamp = Lamp(position=(0.3, 0.0, 0.0))
    SimulatedWorld(scene="brick", distance=3.0, size=(64, 48), water=water, lamp=lamp).components()  # compile

    def new_scene(scene="brick", gate=None):
        t0 = time.perf_counter()
        w = SimulatedWorld(scene=scene, distance=3.0, size=(640, 480), water=water, lamp=lamp, slabs=32, gate_width=gate)
        t1 = time.perf_counter()
        w.components()
        return t1 - t0, time.perf_counter() - t1

    print("new 640x480x3 scene, 32 slabs, Jerlov II (backscatter and forward blur on):")
    for scene, gate in (("brick", None), ("ring", None), ("plate", None), ("brick", 0.05)):
        runs = [new_scene(scene, gate) for _ in range(args.repeat)]
        trace, form = min(r[0] for r in runs), min(r[1] for r in runs)
        label = f"{scene}{' gated' if gate else ''}"
        print(f"  {label:14s} ray casting {trace * 1e3:6.0f} ms + image formation {form * 1e3:6.0f} ms = "
              f"{(trace + form):.2f} s   goal ≤ 1 s: {'met' if trace + form <= 1 else 'NOT met'}")

    world = SimulatedWorld(scene="seabed", distance=3.0, size=(1280, 720), water=water, lamp=lamp)
    out = np.empty((720, 1280, 3), np.uint16)
    world.frame(0, out=out)
    index = iter(range(1, 10**6))
    t_frame, t_frame_med = best_time(lambda: world.frame(next(index), out=out), args.repeat * 6)
    rng = np.random.default_rng(0)
    normals = np.empty(out.size, np.float32)
    t_numpy, _ = best_time(lambda: rng.standard_normal(out.size, dtype=np.float32, out=normals), args.repeat * 6)
    print("static 1280x720x3 scene, new noisy 16-bit frames:")
    print(f"  uwcam frame {t_frame * 1e3:.1f} ms (median {t_frame_med * 1e3:.1f} ms) = {1 / t_frame:.0f} fps "
          f"(median {1 / t_frame_med:.0f} fps); goal ≥ 30 fps: {'met' if 1 / t_frame_med >= 30 else 'NOT met'}")
    print(f"  numpy drawing the same {out.size:,} normal deviates alone: {t_numpy * 1e3:.1f} ms "
          f"(uwcam's whole frame is {t_frame / t_numpy:.2f}× that)")


if __name__ == "__main__":
    main()
