"""The UML route's ptrace shim (scripts/vm/uml-xstate.c) on a host whose XSAVE area is longer than the buffer.

User-Mode Linux 6.1 restores its guests' FPU state with ``PTRACE_SETREGSET``
and a 2696-byte buffer; a host whose XSAVE area is longer (AMX: 11008 bytes)
refuses it with EFAULT and UML panics at boot. ``scripts/vm/xstate-check.c``
reproduces that on any x86-64 host with a buffer shorter than this host's
area; the shim must make the same call succeed and set the register.
"""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
from pathlib import Path

import pytest

VM = Path(__file__).resolve().parents[1] / "scripts" / "vm"

pytestmark = pytest.mark.skipif(platform.machine() != "x86_64" or shutil.which("cc") is None,
                                reason="needs an x86-64 host with a C compiler")


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    out = tmp_path_factory.mktemp("xstate")
    shim, check = out / "uml-xstate.so", out / "xstate-check"
    subprocess.run(["cc", "-O2", "-Wall", "-Werror", "-shared", "-fPIC", "-o", str(shim),
                    str(VM / "uml-xstate.c"), "-ldl"], check=True)
    subprocess.run(["cc", "-O2", "-Wall", "-Werror", "-o", str(check), str(VM / "xstate-check.c")], check=True)
    return shim, check


def _run(check: Path, length: int, preload: Path | None = None, **env: str) -> subprocess.CompletedProcess:
    environ = {**os.environ, "XSTATE_CHECK_LEN": str(length), **env}
    environ.pop("LD_PRELOAD", None)
    if preload is not None:
        environ["LD_PRELOAD"] = str(preload)
    r = subprocess.run([str(check)], env=environ, capture_output=True, text=True, timeout=30)
    if r.returncode == 2:
        pytest.skip(f"ptrace unavailable here: {r.stdout.strip()}")
    return r


@pytest.mark.parametrize("length", [576, 832, 1088])
def test_a_short_buffer_is_refused_by_the_host_and_taken_through_the_shim(built, length: int) -> None:
    shim, check = built
    plain = _run(check, length)
    assert plain.returncode == 1 and "errno 14" in plain.stdout, plain.stdout
    shimmed = _run(check, length, shim)
    assert shimmed.returncode == 0 and "XMM0 set" in shimmed.stdout, shimmed.stdout


@pytest.mark.parametrize("pad", ["", "always"])
def test_a_whole_buffer_passes_with_and_without_padding(built, pad: str) -> None:
    shim, check = built
    r = _run(check, 1 << 15, shim, UML_XSTATE_PAD=pad)  # clamped to the host's area by the kernel
    assert r.returncode == 0 and "XMM0 set" in r.stdout, r.stdout
