"""The benchmark and study scripts run (tiny settings), so they cannot rot unnoticed."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_accuracy_study_quick_run_writes_report_and_plots(tmp_path):
    subprocess.run([sys.executable, str(ROOT / "bench" / "accuracy_study.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, timeout=600)
    report = (tmp_path / "REPORT.md").read_text()
    assert "## 2. Backscatter" in report and "Published:" in report
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results) == {"1", "2", "3", "4", "seconds", "size"}
    assert len(list(tmp_path.glob("*.png"))) == 4
    # Condition 1 without scattering: fusion no worse than the best pair at every noise level.
    for row in results["1"]["levels"].values():
        assert row["fusion"]["rms"] <= 1.05 * min(row[p]["rms"] for p in ("R/G", "R/B", "G/B"))


@pytest.mark.slow
def test_fusion_benchmark_runs(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_fusion.py"), "--size", "320x240", "--repeat", "3"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "× memcopy" in out and "straightforward numpy" in out
    assert "calibration variance step, 1280x720" in out and "blocks vs every pixel" in out


@pytest.mark.slow
def test_daemon_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_daemon.py"), "--rigs", "replay", "--size", "160x120",
                          "--fps", "20", "--frames", "2", "--seconds", "2", "--startup-seconds", "4"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "first range" in out and "resident memory peak" in out and "processed" in out


@pytest.mark.slow
def test_calibration_study_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "calibration_study.py"), "--trials", "3", "--size", "160x120"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "z-score sd" in out and "reported sigma / spread over calibrations" in out


@pytest.mark.slow
def test_water_study_runs_and_judges_its_goals():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "water_study.py"), "--quick"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "## compensated" in out and "## gated" in out and "## Goals" in out
    assert "jerlov-II, lamp 0.3 m, compensated, 3 m:" in out and ("met" in out or "NOT met" in out)


@pytest.mark.slow
def test_water_study_runs_the_goal_cell_on_other_sensors():
    """Small frames, one water and offset: the goal cell again on every other sensor, calibrated
    with each rig (the study's large black patch, and the grey plate's 10 cm one), each line with
    its spread and how many sensors met the goal; and the goal cell itself with the grey plate."""
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "water_study.py"), "--waters", "jerlov-II", "--offsets", "0.3",
                          "--no-pairs", "--size", "80x60", "--frames", "2"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    lines = [line for line in out.splitlines() if "on 12 other sensors" in line]
    assert [line.split(",")[2].strip() for line in lines] == ["compensated ×16"] * 6, out
    assert [line.split(",")[4].split(")")[0].strip() for line in lines] == (
        ["calibrated with the grey-plate-large-patch rig"] * 3 + ["calibrated with the grey-plate rig"] * 3), lines
    assert all("rig) on 12 other sensors" in line and "sd " in line and " of 12" in line for line in lines), lines
    small = [line for line in out.splitlines() if "calibrated with the grey-plate rig instead" in line]
    assert len(small) == 1 and all(f"{d} m: median" in small[0] for d in (3, 5, 7)), small
    assert "on 12 other sensors" not in subprocess.run(
        [sys.executable, str(ROOT / "bench" / "water_study.py"), "--waters", "jerlov-II", "--offsets", "0.3", "--no-pairs",
         "--no-sensors", "--size", "80x60", "--frames", "2"], check=True, capture_output=True, text=True, timeout=600).stdout


@pytest.mark.slow
def test_orientation_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_orientation.py"), "--size", "320x240", "--repeat", "2",
                          "--blocks", "16"], check=True, capture_output=True, text=True, timeout=600).stdout
    assert "× ranging" in out and "within 2°" in out
    row = out.strip().splitlines()[-1].split()
    assert row[0] == "16" and row[3] == "100.0%"  # every block of the tilted plane gets an angle


@pytest.mark.slow
def test_compensation_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_compensation.py"), "--size", "320x180", "--frames", "3",
                          "--distances", "3"], check=True, capture_output=True, text=True, timeout=600).stdout
    row = [line.split() for line in out.splitlines() if line.strip().startswith("3m")]
    assert "compensated ms" in out and len(row) == 1 and len(row[0]) == 5, out
    assert float(row[0][2]) > float(row[0][1]) > 0  # compensation costs more than plain ranging


@pytest.mark.slow
def test_temporal_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_temporal.py"), "--size", "160x120", "--distance", "3",
                          "--water", "jerlov-IA", "--seconds", "1.5", "--frames", "3", "--max-frames", "8"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith(("one frame", "fused"))}
    assert rows["one"][2] == "100.0%" and rows["fused"][1] == "100.0%", out  # the grey seabed at 3 m, every pixel
    assert float(rows["fused"][6]) >= 4, out  # frames per pixel, median
    assert "fusion stage:" in out


@pytest.mark.slow
def test_recording_budget_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_recording_budget.py"), "--frames", "1"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "1280×720: raw frame 5.53 MB" in out and "1920×1080: raw frame 12.44 MB" in out  # 2 bytes × 3 channels a pixel
    assert out.count("% of raw frames") == 10


@pytest.mark.slow
def test_zenoh_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_zenoh.py"), "--budgets", "128", "--seconds", "2",
                          "--size", "160x120", "--fps", "10"],
                         check=True, capture_output=True, text=True, timeout=600).stdout
    assert "range/summary" in out and "status" in out and "kbit/s of 128" in out


@pytest.mark.slow
@pytest.mark.browser
def test_soak_runs_and_judges():
    """A 45 s soak (three samples): the table and every verdict are printed; whether they pass on
    a loaded test machine is the long soak's question, not this one's."""
    result = subprocess.run([sys.executable, str(ROOT / "bench" / "soak.py"), "--minutes", "0.75", "--sample-s", "15",
                             "--silent-s", "20"], capture_output=True, text=True, timeout=600)
    out = result.stdout
    assert "rss_MB" in out and "reader_age_s" in out, result.stderr[-2000:]
    for verdict in ("fps within 10 %", "RSS within 10 %", "no recorded frame lost unaccounted",
                    "silent lamp shown, then answering", "slow reader's newest map", "page open throughout"):
        assert f"  {verdict}" in out, out
    assert result.returncode == (0 if "soak passed" in out else 1), out


def test_soak_judges_fps_over_whole_scene_cycles():
    """The soak's fps windows: frames over each whole altitude cycle of the default scene, from
    the samples at the cycle's end, a trailing partial cycle left out. Counts written out by hand:
    30-s samples, 270 frames in each of the first cycle's, 240 in the second's, 300 in the third's."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("soak", ROOT / "bench" / "soak.py")
    soak = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(soak)
    assert soak.scene_cycle_s() == 120.0  # uwcam/config.py default_config: altitude_period 120 s
    per_sample = [270] * 4 + [240] * 4 + [300] * 4 + [500] * 2
    rows, processed = [], 1000
    for i, n in enumerate(per_sample, start=1):
        processed += n
        rows.append({"t_s": 30.0 * i, "processed": processed, "fps": n / 30.0})
    assert [rate for rate, _ in soak.cycle_windows(rows, 120.0)] == pytest.approx([1080 / 120, 960 / 120, 1200 / 120])
    # On a machine of constant speed: the second cycle's core ran 10 % slower (its probe took
    # 11 ms, the others 10 ms; the median is 10), so its 8 fps count as 8.8.
    for row, probe_ms in zip(rows, [10.0] * 4 + [11.0] * 4 + [10.0] * 6):
        row["probe_ms"] = probe_ms
    assert soak.machine_normalised(soak.cycle_windows(rows, 120.0)) == pytest.approx([9.0, 8.8, 10.0])


@pytest.mark.slow
def test_adaptive_smoothing_benchmark_runs():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_adaptive_smoothing.py"), "--size", "160x120",
                          "--repeat", "1", "--frames", "1"], check=True, capture_output=True, text=True, timeout=600).stdout
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.split() and line.split()[0] in
            ("none", "mean", "adaptive", "far")}
    assert "smoothing's own cost" in out and {"none", "mean", "adaptive"} <= set(rows), out
    far = [line.split() for line in out.splitlines() if line.strip().startswith("adaptive") and "%" in line]
    assert far and float(far[-1][-1].rstrip("%")) > 50, out  # most far pixels reach the target
