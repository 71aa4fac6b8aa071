"""Help is instant: ``online-id COMMAND --help`` imports none of the heavy libraries (scipy, numba, python-can,
cantools, asammdf, matplotlib, dask), each command in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys

import pytest

from online_id.cli import SUBCOMMANDS

HEAVY = ("scipy", "numba", "can", "cantools", "asammdf", "matplotlib", "dask", "pandas", "filterpy")

PROBE = """
import sys
from online_id.cli import main
try:
    main([sys.argv[1], "--help"])
except SystemExit:
    pass
print("LOADED", " ".join(sorted(m for m in {heavy!r} if m in sys.modules)))
"""


@pytest.mark.parametrize("command", sorted(SUBCOMMANDS))
def test_help_imports_no_heavy_library(command):
    out = subprocess.run([sys.executable, "-c", PROBE.format(heavy=HEAVY), command], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "usage: online-id " + command in out.stdout, out.stdout[:500]
    loaded = out.stdout.rsplit("LOADED", 1)[1].split()
    assert loaded == [], f"online-id {command} --help imports {loaded}"


def test_top_level_help_imports_no_heavy_library():
    out = subprocess.run([sys.executable, "-c", PROBE.replace("main([sys.argv[1], \"--help\"])", "main([\"--help\"])")
                          .format(heavy=HEAVY), "x"], capture_output=True, text=True, timeout=120)
    assert "COMMAND" in out.stdout
    assert out.stdout.rsplit("LOADED", 1)[1].split() == []
