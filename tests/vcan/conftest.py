"""The vcan tier: tests over a real SocketCAN interface (``vcan0``).

Every test in this folder is marked ``vcan`` automatically, so
``pytest -m "not vcan"`` leaves them out and ``pytest -m vcan tests/vcan``
runs them alone. ``make test`` runs them natively where ``vcan0`` exists or
can be created (a bench PC: ``sudo modprobe vcan``), else inside another
kernel that has CAN (``scripts/vm-run``: QEMU with KVM, User-Mode Linux, or
QEMU emulating the CPU; docs/testing.md).

Without a usable ``vcan0`` the tests skip with the reason; with
``ONLINE_ID_VCAN_REQUIRED=1`` (set by ``scripts/test-vcan``, which has made
sure the interface exists) they fail instead, so a broken harness cannot pass
as all-skipped.

Fixtures
--------
vcan0
    The channel name ``"vcan0"``, once it is known to work.
vcan0_bus
    An open python-can socketcan bus on ``vcan0``, shut down afterwards.
recv_frames
    ``recv_frames(bus, count, timeout_s=..., arbitration_ids=None)``: the next
    ``count`` frames, in arrival order (fails on timeout).
run_process
    ``run_process(argv, timeout_s=...)``: start a subprocess (output to pipes,
    no stdin, CAN_* variables removed); killed at teardown if still running.
online_id_argv
    The argv prefix that starts the project's CLI (``online-id``).
can_utils
    Skips the test unless can-utils' ``cansend`` and ``candump`` are installed.

Inside User-Mode Linux every system call is trapped (about 1,000 frames/s
with python-can); where QEMU emulates the CPU, Python runs 15-25 times
slower than natively (``VM_RUN_SLOW`` stretches the time-outs). A fast sender
can overrun a slow reader's socket buffer. Assert behaviour, never timing,
and keep timeouts generous.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import can
import pytest

VCAN_DIR = Path(__file__).parent
CHANNEL = "vcan0"
REQUIRED_ENV = "ONLINE_ID_VCAN_REQUIRED"
#: How much slower than natively this kernel runs Python (scripts/vm-run sets it: 5 where QEMU
#: emulates the CPU); every time-out of the tier is stretched by it.
SLOW = float(os.environ.get("VM_RUN_SLOW", "1"))
#: Generous default for receive and subprocess timeouts (UML is slow).
TIMEOUT_S = 30.0 * SLOW

_probe_result: dict[str, str | None] = {}


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark every test under tests/vcan ``vcan`` (before ``-m`` deselects)."""
    for item in items:
        if VCAN_DIR in item.path.parents:
            item.add_marker(pytest.mark.vcan)


def _unusable_reason(channel: str) -> str | None:
    """Why ``channel`` cannot be opened as a socketcan bus, or None if it can."""
    if channel not in _probe_result:
        try:
            bus = can.Bus(interface="socketcan", channel=channel, ignore_config=True)
        except (OSError, can.CanError) as err:
            _probe_result[channel] = (
                f'no usable SocketCAN interface "{channel}" ({err}); the vcan tier '
                f"needs one: run `make test` (it runs this tier in another kernel "
                f"when this one has no vcan), or `sudo modprobe vcan && sudo ip link "
                f"add dev {channel} type vcan && sudo ip link set up {channel}`"
            )
        else:
            bus.shutdown()
            _probe_result[channel] = None
    return _probe_result[channel]


@pytest.fixture
def vcan0() -> str:
    """The name of a usable SocketCAN vcan interface; skips (or fails) if none."""
    reason = _unusable_reason(CHANNEL)
    if reason is not None:
        if os.environ.get(REQUIRED_ENV) == "1":
            pytest.fail(f"{REQUIRED_ENV}=1 but {reason}")
        pytest.skip(reason)
    return CHANNEL


@pytest.fixture
def vcan0_bus(vcan0: str) -> Iterator[can.BusABC]:
    """An open python-can socketcan bus on vcan0 (not receiving its own frames)."""
    bus = can.Bus(interface="socketcan", channel=vcan0, ignore_config=True)
    try:
        yield bus
    finally:
        bus.shutdown()


def _recv_frames(
    bus: can.BusABC,
    count: int,
    timeout_s: float = TIMEOUT_S,
    arbitration_ids: Sequence[int] | None = None,
) -> list[can.Message]:
    """Receive ``count`` frames (only the given ids, if any) or fail after ``timeout_s``."""
    wanted = None if arbitration_ids is None else set(arbitration_ids)
    frames: list[can.Message] = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < count:
        left_s = deadline - time.monotonic()
        if left_s <= 0:
            pytest.fail(
                f"Expected {count} frames on {bus.channel_info} within {timeout_s} s, "
                f"but got {len(frames)}: {frames}"
            )
        frame = bus.recv(timeout=min(left_s, 1.0))
        if frame is None or frame.is_error_frame:
            continue
        if wanted is None or frame.arbitration_id in wanted:
            frames.append(frame)
    return frames


@pytest.fixture
def recv_frames() -> Callable[..., list[can.Message]]:
    """The receive helper: ``recv_frames(bus, count, timeout_s=30, arbitration_ids=None)``."""
    return _recv_frames


def _child_env() -> dict[str, str]:
    """The environment for subprocesses: python-can's CAN_* settings removed."""
    return {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}


@pytest.fixture
def run_process() -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Start subprocesses (text pipes, no stdin); any still running at teardown is killed.

    Wait for one with ``proc.communicate(timeout=...)``; the caller asserts
    on ``proc.returncode`` and the output.
    """
    started: list[subprocess.Popen[str]] = []

    def start(argv: Sequence[str | os.PathLike[str]], **kwargs: object) -> subprocess.Popen[str]:
        options: dict[str, object] = {
            "stdin": subprocess.DEVNULL,
            "stdout": subprocess.PIPE,
            "stderr": subprocess.PIPE,
            "text": True,
            "env": _child_env(),
        }
        options.update(kwargs)
        proc = subprocess.Popen([os.fspath(a) for a in argv], **options)  # type: ignore[call-overload]
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=TIMEOUT_S)


@pytest.fixture
def online_id_argv() -> list[str]:
    """argv prefix of the project's CLI: the venv's ``online-id`` script if present."""
    script = Path(sys.executable).with_name("online-id")
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-m", "online_id"]


@pytest.fixture
def can_utils() -> None:
    """Skip unless can-utils' cansend and candump are on PATH.

    (scripts/install-system-deps installs them when run as root, as in CI.)
    """
    missing = [tool for tool in ("cansend", "candump") if shutil.which(tool) is None]
    if missing:
        pytest.skip(
            f"can-utils missing ({', '.join(missing)}): run scripts/install-system-deps "
            f"as root, or apt-get install can-utils"
        )
