"""Optional parts (uwcam/extras.py): the daemon ranges without them, and a feature that needs an
absent one stops with one line naming the extra to install."""

import json
import sys

import pytest

from tests.fresh_install import UserDaemon
from uwcam.fileio import UserInputError

OPTIONAL_MODULES = ("distributed", "dask", "matplotlib", "zenoh")

HIDE = (
    "import importlib.abc, sys\n"
    "class Hide(importlib.abc.MetaPathFinder):\n"
    "    def find_spec(self, name, path=None, target=None):\n"
    f"        if name.split('.')[0] in {OPTIONAL_MODULES!r}:\n"
    "            raise ModuleNotFoundError(name)\n"
    "sys.meta_path.insert(0, Hide())\n"
)


@pytest.mark.slow
def test_the_daemon_ranges_and_stops_cleanly_without_the_optional_parts(tmp_path):
    """A lean install (`deploy/install.sh lean`): the embedded default serves, ranges, and exits 0
    on Ctrl-C with none of the optional libraries importable."""
    script = HIDE + (
        "from uwcam.cli import main\n"
        "code = main(sys.argv[1:])\n"
        f"loaded = sorted(m for m in sys.modules if m.split('.')[0] in {OPTIONAL_MODULES!r})\n"
        "print('optional modules loaded:', loaded, flush=True)\n"
        "sys.exit(code)\n")
    home = tmp_path / "home"
    home.mkdir()
    daemon = UserDaemon(tmp_path, home, f"{sys.executable} -c \"{script}\" run")
    try:
        daemon.wait_until(lambda: json.loads(daemon.get("/api/v1/status"))["frames"]["processed"] > 5,
                          180.0, "five ranged frames")
        assert daemon.ctrl_c() == 0, daemon.output[-3000:]
    finally:
        daemon.kill()
    assert "optional modules loaded: []" in daemon.output, daemon.output[-3000:]


@pytest.mark.parametrize("extra, module", [("cluster", "distributed"), ("reports", "matplotlib"), ("zenoh", "zenoh")])
def test_a_missing_extra_is_named_in_one_line(monkeypatch, extra, module):
    from uwcam.extras import require_extra

    monkeypatch.setitem(sys.modules, module, None)  # None in sys.modules: the import fails
    with pytest.raises(UserInputError) as err:
        require_extra(extra)
    text = str(err.value)
    assert "\n" not in text and f"pip install 'uwcam[{extra}]'" in text and module in text


def test_reprocessing_on_a_cluster_without_distributed_says_what_to_install(monkeypatch):
    from uwcam.recording.reprocess import _in_order

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(UserInputError, match=r"uwcam\[cluster\]"):
        list(_in_order([object()], lambda part, kernel_threads=None: part, scheduler="local", workers=1))


def test_plate_artwork_without_matplotlib_says_what_to_install(monkeypatch, tmp_path):
    from uwcam.calibration.rig import builtin_rig_path, load_rig
    from uwcam.calibration.artwork import write_artwork

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    rig = load_rig(builtin_rig_path("grey-plate"))
    with pytest.raises(UserInputError, match=r"uwcam\[reports\]"):
        write_artwork(rig, tmp_path / "plate.pdf")
    assert not (tmp_path / "plate.pdf").exists()


def test_a_calibration_report_without_matplotlib_is_refused_before_the_fit(monkeypatch, tmp_path, capsys):
    from uwcam.cli import main

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    frame = tmp_path / "f.npy"
    import numpy as np

    np.save(frame, np.full((8, 8, 3), 1000, np.uint16))
    code = main(["calibrate", str(frame), "--distance", "1", "-o", str(tmp_path / "p.yaml"),
                 "--report", str(tmp_path / "r.html")])
    err = capsys.readouterr().err
    assert code != 0 and "uwcam[reports]" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "p.yaml").exists() and not (tmp_path / "r.html").exists()
