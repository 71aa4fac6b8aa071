"""The vcan harness itself: real clients, written by others, talk over vcan0.

python-can's socketcan backend, can-utils' cansend/candump and python-can's
``can.player`` must all see each other's frames. If these fail, the tier's
environment is broken, not the project.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import can
import pytest

TIMEOUT_S = 30.0 * float(os.environ.get("VM_RUN_SLOW", "1"))  # stretched where the CPU is emulated


def test_python_can_round_trip(vcan0: str, vcan0_bus: can.BusABC, recv_frames: Callable) -> None:
    with can.Bus(interface="socketcan", channel=vcan0, ignore_config=True) as sender:
        sent = [
            can.Message(arbitration_id=0x100 + i, data=bytes([i, 0xAA, 0x55]), is_extended_id=False)
            for i in range(5)
        ]
        sent.append(can.Message(arbitration_id=0x18FEF100, data=b"\x01\x02", is_extended_id=True))
        for frame in sent:
            sender.send(frame)

    got = recv_frames(vcan0_bus, len(sent))
    assert [(f.arbitration_id, f.is_extended_id, bytes(f.data)) for f in got] == [
        (f.arbitration_id, f.is_extended_id, bytes(f.data)) for f in sent
    ]


@pytest.mark.usefixtures("can_utils")
def test_cansend_received_by_python_can(
    vcan0: str, vcan0_bus: can.BusABC, recv_frames: Callable, run_process: Callable
) -> None:
    proc = run_process(["cansend", vcan0, "123#DEADBEEF"])
    out, err = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == 0, f"cansend failed: {err}"

    (frame,) = recv_frames(vcan0_bus, 1, arbitration_ids=[0x123])
    assert not frame.is_extended_id
    assert bytes(frame.data) == bytes.fromhex("DEADBEEF")


@pytest.mark.usefixtures("can_utils")
def test_python_can_received_by_candump(
    vcan0: str, vcan0_bus: can.BusABC, run_process: Callable
) -> None:
    # -n 1: exit after one frame; the filter keeps stray traffic out.
    proc = run_process(["candump", "-L", "-n", "1", f"{vcan0},321:7FF"])
    # candump prints nothing until its socket is bound; no portable readiness
    # signal, so send until it has exited (each send is a fresh chance).
    frame = can.Message(arbitration_id=0x321, data=b"\x01\x02\x03\x04", is_extended_id=False)
    for _ in range(int(TIMEOUT_S / 0.2)):
        vcan0_bus.send(frame)
        try:
            out, err = proc.communicate(timeout=0.2)
            break
        except subprocess.TimeoutExpired:
            continue
    else:
        pytest.fail(f"candump printed no frame within {TIMEOUT_S} s")
    assert proc.returncode == 0, f"candump failed: {err}"
    # candump -L: "(1700000000.123456) vcan0 321#01020304"
    fields = out.split()
    assert fields[1:] == [vcan0, "321#01020304"], out


def test_can_player_replays_log_in_order(
    vcan0: str, vcan0_bus: can.BusABC, recv_frames: Callable, run_process: Callable, tmp_path: Path
) -> None:
    log_path = tmp_path / "replay.log"
    frames = [
        can.Message(
            timestamp=1_700_000_000.0 + 0.005 * i,
            arbitration_id=0x200 + (i % 3),
            data=bytes([i, 255 - i, i * 7 % 256]),
            is_extended_id=False,
            channel=vcan0,
        )
        for i in range(20)
    ]
    with can.CanutilsLogWriter(log_path, channel=vcan0) as writer:
        for frame in frames:
            writer.on_message_received(frame)

    proc = run_process(
        [sys.executable, "-m", "can.player", "-i", "socketcan", "-c", vcan0, str(log_path)]
    )
    out, err = proc.communicate(timeout=TIMEOUT_S * 2)
    assert proc.returncode == 0, f"can.player failed:\n{out}\n{err}"

    got = recv_frames(vcan0_bus, len(frames), arbitration_ids=[0x200, 0x201, 0x202])
    assert [(f.arbitration_id, bytes(f.data)) for f in got] == [
        (f.arbitration_id, bytes(f.data)) for f in frames
    ]


def test_online_id_cli_runs_here(vcan0: str, run_process: Callable, online_id_argv: list[str]) -> None:
    # The project's console script starts in this tier's environment (inside
    # UML too): the pattern for service tests that drive `online-id`.
    proc = run_process([*online_id_argv, "--version"])
    out, err = proc.communicate(timeout=TIMEOUT_S * 4)
    assert proc.returncode == 0, f"online-id --version failed:\n{out}\n{err}"
    assert out.startswith("online-id "), out


def test_kernel_drops_are_counted_on_a_full_receive_buffer(vcan0: str) -> None:
    """A reader that does not read: its small buffer fills, and CanBus.dropped() counts what the kernel threw away."""
    from online_id.io.bus import CanBus

    reader = CanBus("socketcan", vcan0, receive_buffer_bytes=4096)  # a few frames' worth
    try:
        assert reader.dropped() == 0
        n = 500
        with can.Bus(interface="socketcan", channel=vcan0, ignore_config=True) as sender:
            for i in range(n):
                sender.send(can.Message(arbitration_id=0x200, data=bytes([i % 256]), is_extended_id=False))
        got = 0
        while reader.recv(0.2) is not None:
            got += 1
        dropped = reader.dropped()
        assert dropped is not None and dropped > 0
        assert got + dropped == n
    finally:
        reader.close()
