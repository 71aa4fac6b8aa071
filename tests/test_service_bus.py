"""How the service meets a bus it cannot open: heal-able faults are retried, the rest end at once with the fix."""

from __future__ import annotations

import io
import time

import pytest

from online_id.config import BusSettings, Settings
from online_id.errors import BusError
from online_id.io.bus import CanBus
from online_id.service.offload import InlineWorker
from online_id.service.live import Service


def _service(factory, reopen_max_s: float = 30.0) -> tuple[Service, io.StringIO]:
    log = io.StringIO()
    s = Settings(bus=BusSettings(interface="virtual", channel="x", reopen_max_s=reopen_max_s))
    return Service(s, log=log, bus_factory=factory, worker=InlineWorker()), log


@pytest.mark.parametrize("interface,channel,fix", [
    ("socketcan", "vcan0", "modprobe can-raw"),  # this kernel has no AF_CAN
    ("no-such-interface", "x", "check bus.interface"),
])
def test_a_bus_that_cannot_heal_ends_the_service_at_once_with_the_fix(interface, channel, fix) -> None:
    import socket

    if interface == "socketcan" and hasattr(socket, "AF_CAN"):
        try:
            socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
            pytest.skip("this kernel has SocketCAN")
        except OSError:
            pass
    calls = []

    def factory() -> CanBus:
        calls.append(time.monotonic())
        return CanBus(interface, channel)

    svc, log = _service(factory)
    t0 = time.monotonic()
    assert svc.run(max_s=60) == 2
    assert time.monotonic() - t0 < 5 and len(calls) == 1  # no retry loop
    lines = log.getvalue().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("online-id: bus down: cannot open CAN bus") and fix in lines[0]


def test_a_missing_optional_package_is_named(monkeypatch) -> None:
    import can.interfaces.udp_multicast.utils as utils

    monkeypatch.setattr(utils, "msgpack", None)
    with pytest.raises(BusError, match="install the Python package msgpack") as info:
        CanBus("udp_multicast", "239.74.163.99")
    assert info.value.permanent


def test_a_bus_that_may_come_up_is_retried_within_the_limits() -> None:
    calls = []

    def down() -> CanBus:
        calls.append(time.monotonic())
        err = BusError("cannot open CAN bus socketcan:can0: [Errno 19] No such device")
        err.permanent = False
        raise err

    svc, log = _service(down, reopen_max_s=1.0)  # bus.reopen_max_s
    t0 = time.monotonic()
    assert svc.run(max_s=60) == 1
    assert 1.0 <= time.monotonic() - t0 < 10 and len(calls) >= 3  # back-off 0.1, 0.2, 0.4, ...
    assert "gave up after 1 s (bus.reopen_max_s)" in log.getvalue()
    svc, log = _service(down, reopen_max_s=30.0)
    t0 = time.monotonic()
    assert svc.run(max_s=1.5) == 1  # --max-seconds bounds the retries too
    assert time.monotonic() - t0 < 6
    assert "stopped retrying at the time limit" in log.getvalue()


def test_a_bus_that_comes_up_late_is_used() -> None:
    calls = []

    def late() -> CanBus:
        calls.append(time.monotonic())
        if len(calls) < 3:
            err = BusError("cannot open CAN bus virtual:x: not yet")
            err.permanent = False
            raise err
        return CanBus("virtual", "late-bus")

    svc, log = _service(late)
    assert svc.run(max_s=1.0) == 0
    assert len(calls) == 3 and "listening on virtual:x" in log.getvalue()
