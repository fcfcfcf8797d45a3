"""Memory handed back to the system: the compiler library's code pages once kernels are loaded."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from uwcam.runtime.memory import read_only_mappings


def test_read_only_mappings_are_parsed_from_a_maps_table(tmp_path):
    maps = tmp_path / "maps"
    maps.write_text(textwrap.dedent("""\
        7f0000000000-7f0000200000 r--p 00000000 08:01 12 /venv/lib/libllvmlite.so
        7f0000200000-7f0005000000 r-xp 00200000 08:01 12 /venv/lib/libllvmlite.so
        7f0005000000-7f0005100000 rw-p 04e00000 08:01 12 /venv/lib/libllvmlite.so
        7f0006000000-7f0006001000 r-xp 00000000 08:01 13 /venv/lib/libother.so
        7f0007000000-7f0007100000 rw-p 00000000 00:00 0
        7f0008000000-7f0008001000 r--p 00000000 08:01 14 /path with spaces/libllvmlite.so (deleted)
        """))
    assert read_only_mappings("libllvmlite", str(maps)) == [
        (0x7F0000000000, 0x7F0000200000), (0x7F0000200000, 0x7F0005000000), (0x7F0008000000, 0x7F0008001000)]
    assert read_only_mappings("libllvmlite", str(tmp_path / "absent")) == []


PROBE = textwrap.dedent("""
    import json, numpy as np
    from numba import njit
    from uwcam.runtime.memory import read_only_mappings, release_compiler_pages

    def resident_kb(part, field):
        # A field of /proc/self/smaps summed over this process's read-only mappings of the library
        spans, kb, current = set(read_only_mappings(part)), 0, None
        for line in open("/proc/self/smaps"):
            head = line.split()[0]
            if "-" in head and not head.endswith(":"):
                current = tuple(int(v, 16) for v in head.split("-"))
            elif head == field + ":" and current in spans:
                kb += int(line.split()[1])
        return kb

    @njit
    def total(a):
        s = 0.0
        for v in a:
            s += v
        return s

    a = np.arange(1000.0)
    first = total(a)
    before = resident_kb("libllvmlite", "Rss")
    advised = release_compiler_pages()
    after = resident_kb("libllvmlite", "Private_Clean")
    again = total(a)  # compiled code still runs
    print(json.dumps({"before": before, "after": after, "advised": advised, "first": first, "again": again}))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="MADV_PAGEOUT and /proc/self/smaps are Linux's")
def test_the_compilers_code_leaves_the_resident_set_and_compiled_kernels_still_run():
    pytest.importorskip("numba")  # where numba has no wheels there is no compiler to release
    import json

    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["first"] == r["again"] == sum(range(1000))
    assert r["advised"] > 0 and r["before"] > 20_000  # tens of MB of LLVM were resident
    # The clean pages of the library that this process alone maps are gone (pages that another
    # process maps too, pytest's own here, stay: the kernel keeps them for that process). The
    # advice is best effort: a page busy at that instant may stay (one 4 kB page was seen once).
    assert r["after"] <= max(64, 0.01 * r["before"])  # kB: from tens of MB to next to nothing
