"""The bus adapter's send: the bytes python-can would write, written at once, or python-can's own send."""

from __future__ import annotations

import gc
import logging
import socket
import time

import can
import numpy as np
import pytest
from can.interfaces.socketcan.socketcan import build_can_frame
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from online_id.errors import BusError
from online_id.io.bus import CanBus, _Wire


def _frames(seed: int, n: int = 300) -> list[tuple[int, bool, bytes]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        extended = bool(rng.integers(2))
        ident = int(rng.integers(0, 1 << 29 if extended else 1 << 11))
        out.append((ident, extended, bytes(rng.integers(0, 256, int(rng.integers(0, 9))).tolist())))
    return out + [(0x300, False, bytes(8)), (0x7FF, False, b"\xff" * 8), ((1 << 29) - 1, True, b"")]


@pytest.mark.parametrize("pack", [pack_message, build_can_frame], ids=["udp_multicast", "socketcan"])
@pytest.mark.parametrize("seed", [1, 2])
def test_the_wire_writes_what_python_can_packs(pack, seed: int) -> None:
    """Standard and extended IDs, 0-8 data bytes: every write is python-can's packing of that frame."""
    written: list[bytes] = []
    wire = _Wire(pack, lambda data: written.append(data) or True)
    frames = _frames(seed)
    for ident, extended, data in frames:
        assert wire.send(ident, data, extended)
    assert written == [pack(can.Message(arbitration_id=i, is_extended_id=x, data=d)) for i, x, d in frames]


def test_a_packing_the_wire_cannot_reproduce_goes_to_python_can() -> None:
    """A packing whose bytes are not the probe's with the data put in (here: a running count in them) has no
    template: the wire writes nothing and says so, and the bus sends through python-can."""
    count = iter(range(10**6))
    written: list[bytes] = []
    wire = _Wire(lambda msg: pack_message(msg) + bytes([next(count) % 256]), written.append)
    assert not wire.send(0x123, b"\x01\x02", False) and not written


def test_a_full_queue_falls_back_to_python_cans_send(monkeypatch) -> None:
    """The wire's write declined (SocketCAN's transmit queue full): python-can's send, which waits, sends it."""
    bus = CanBus("virtual", "wire-fallback")
    sent: list[can.Message] = []
    monkeypatch.setattr(bus._bus, "send", lambda msg, timeout=None: sent.append(msg))
    bus._wire = _Wire(build_can_frame, lambda data: False)
    bus.send(0x301, b"\x05" * 8)
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in sent] == [(0x301, False, b"\x05" * 8)]
    bus.close()


def test_a_failed_write_is_a_bus_error_naming_the_frame() -> None:
    bus = CanBus("virtual", "wire-error")

    def fail(_data: bytes) -> bool:
        raise OSError(100, "Network is down")

    bus._wire = _Wire(build_can_frame, fail)
    with pytest.raises(BusError, match=r"send of ID 0x2A failed: .*Network is down"):
        bus.send(0x2A, b"\x00")
    bus.close()


def test_frames_sent_on_udp_multicast_arrive_as_sent() -> None:
    """Through the kernel: what one bus sends, another receives (IDs, data, extended flag), with the sender's
    template path taken; a frame with a timestamp goes through python-can and arrives alike."""
    group, port = "239.74.163.61", 43161
    rx, tx = CanBus("udp_multicast", group, port=port), CanBus("udp_multicast", group, port=port)
    try:
        assert tx._wire is not None
        frames = _frames(3, 40)
        for ident, extended, data in frames:
            tx.send(ident, data, extended)
        tx.send(0x100, b"\x11" * 8, t_s=12.5)
        got, deadline = [], time.monotonic() + 10.0
        while len(got) < len(frames) + 1 and time.monotonic() < deadline:
            f = rx.recv(0.1)
            if f is not None:
                got.append((f.arbitration_id, f.is_extended, f.data))
        assert got == frames + [(0x100, False, b"\x11" * 8)]
        assert len(tx._wire._templates) > 10
    finally:
        rx.close()
        tx.close()


def test_the_udp_multicast_template_unpacks_as_the_frame() -> None:
    """python-can's receiver reads the bytes back as the frame (a check of the probe's data place)."""
    written: list[bytes] = []
    wire = _Wire(pack_message, lambda data: written.append(data) or True)
    wire.send(0x1ABCDEF, b"\x01\x02\x03", True)
    msg = unpack_message(written[0])
    assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data), msg.dlc) == (0x1ABCDEF, True, b"\x01\x02\x03", 3)


def test_a_socketcan_wire_is_taken_only_for_a_bound_socket() -> None:
    """python-can's SocketCAN bus on no channel (it sends to each frame's own) keeps python-can's send."""
    from can.interfaces.socketcan import SocketcanBus

    class Unbound(SocketcanBus):
        def __init__(self) -> None:  # no kernel socket needed for the check
            self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.channel = ""

    bus = Unbound()
    try:
        assert _Wire.of(bus, 0.1) is None
    finally:
        bus.socket.close()


def _first(rx: CanBus, timeout_s: float = 1.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        f = rx.recv(0.1)
        if f is not None:
            return f
    return None


def test_udp_multicast_runs_are_told_apart_by_port_not_by_group() -> None:
    """Why each live run takes a port of its own (tests/live/harness.py): a bus bound to a port reads what is
    sent to another group on that port, and nothing of the same group on another port."""
    from tests.live.harness import free_udp_port

    port, other = free_udp_port(), free_udp_port()
    for rx_group, rx_port, crosses in (("239.74.163.71", port, True), ("239.74.163.72", other, False)):
        rx, tx = CanBus("udp_multicast", rx_group, port=rx_port), CanBus("udp_multicast", "239.74.163.72", port=port)
        try:
            tx.send(0x11, b"\x01")
            assert (_first(rx) is not None) == crosses
        finally:
            rx.close()
            tx.close()


def test_interface_options_reach_python_can_and_a_wrong_one_is_one_line(caplog) -> None:
    """``bus.options`` go to ``can.Bus`` as the interface's own arguments (here udp_multicast's port); one the
    interface cannot take is a permanent BusError naming bus.options, not a traceback."""
    from tests.live.harness import free_udp_port

    port = free_udp_port()
    rx = CanBus("udp_multicast", "239.74.163.73", options={"port": port})
    tx = CanBus("udp_multicast", "239.74.163.73", port=port)
    try:
        tx.send(0x12, b"\x02")
        f = _first(rx)
        assert f is not None and f.arbitration_id == 0x12
    finally:
        rx.close()
        tx.close()
    for port in (70000, "43113x"):  # out of range; not a number (a service name no system knows)
        with caplog.at_level(logging.WARNING, logger="can"):
            with pytest.raises(BusError, match=r"cannot open CAN bus udp_multicast:239.74.163.73: .*bus.options") as info:
                CanBus("udp_multicast", "239.74.163.73", options={"port": port})
            assert info.value.permanent and "\n" not in str(info.value)
            del info
            gc.collect()
        # the half-made bus was shut down, not left to warn when collected
        assert not [r for r in caplog.records if "not properly shut down" in r.getMessage()]
