"""Every module of uwcam imports on its own, in a fresh interpreter: an import circle that only
bites when a module is the first of its circle to load (uwcam warmup loaded the recorder before the
API, and the API's recordings route took a name from the recorder while it was half-loaded) fails
here, whatever order the rest of the suite happens to import in."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "uwcam"
NOT_ON_ITS_OWN = {
    "uwcam.__main__": "runs the command line",
    "uwcam.optics.kernels_numba": "is loaded through uwcam.optics.kernels, with which it forms a circle (issue #45)",
}


def modules() -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if name not in NOT_ON_ITS_OWN:
            names.append(name)
    return names


@pytest.mark.slow
def test_every_module_imports_on_its_own():
    def load(name: str) -> str | None:
        done = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True, text=True, timeout=120,
                              cwd=PACKAGE.parent.parent)
        return None if done.returncode == 0 else f"{name}: {done.stderr.strip().splitlines()[-1]}"

    with ThreadPoolExecutor(max_workers=2) as pool:
        failures = [f for f in pool.map(load, modules()) if f is not None]
    assert not failures, "\n".join(failures)
    assert len(modules()) > 100
