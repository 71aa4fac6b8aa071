"""The bus adapter's send on a real SocketCAN interface: python-can's bytes from a template, one write each."""

from __future__ import annotations

from collections.abc import Callable

import can

from online_id.io.bus import CanBus


def test_the_adapters_frames_arrive_as_sent(vcan0: str, vcan0_bus: can.BusABC, recv_frames: Callable) -> None:
    """Standard and extended IDs, 0-8 data bytes, sent by the service's adapter (its template path on SocketCAN),
    read back by python-can as sent; one with a timestamp takes python-can's own send."""
    sent = [(0x300 + i, False, bytes(range(i))) for i in range(9)]
    sent += [(0x18FEF100, True, b"\x01\x02"), (0x7FF, False, b"\xff" * 8), (0x1FFFFFFF, True, b"")]
    with CanBus("socketcan", vcan0) as bus:
        assert bus._wire is not None  # the template path is the one under test
        for ident, extended, data in sent:
            bus.send(ident, data, extended)
        bus.send(0x123, b"\x42" * 8, t_s=1.0)
        assert len(bus._wire._templates) == len(sent)
    got = recv_frames(vcan0_bus, len(sent) + 1)
    assert [(f.arbitration_id, f.is_extended_id, bytes(f.data)) for f in got] == sent + [(0x123, False, b"\x42" * 8)]
