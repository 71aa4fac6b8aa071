"""`online-id monitor` marks a frame whose values the DBC does not allow as suspect instead of showing them.

An 8-bit CRC passes one random frame in 256; such a frame decoded as it comes showed ``State 238``.
"""

import json
import os
import threading
import time

import numpy as np

from online_id.cli import main
from online_id.cli.monitor import Watch, line
from online_id.io.bus import CanBus
from online_id.io.crc import crc8_j1850
from online_id.io.dbc import load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.records import EstimateOut, ServiceState, StatusOut

DB = load_dbc(None)


def _watch() -> Watch:
    codec = OutputEncoder(DB)
    return Watch(codec, codec.output_ids(), DB)


def _with_crc(head: bytes) -> bytes:
    return head + bytes([crc8_j1850(head)])


def test_undefined_and_out_of_range_values_are_suspect_not_shown():
    w = _watch()
    good = OutputEncoder(DB).encode(StatusOut(1.0, ServiceState.TRACKING, 0, 0))[0]
    assert "signals" in w.take(0.0, *good)
    status = _with_crc(bytes([238, 0, 0, 0, 0, 0, 0x10]))  # State 238, counter 1
    rec = w.take(0.1, 0x303, status)
    assert "signals" not in rec and "State 238 is not a defined value" in rec["suspect"]
    assert "SUSPECT" in line(rec) and "238" in line(rec) and "values not shown" in line(rec)
    alert = _with_crc(bytes([1, 3, 0, 0, 0xFF, 0x7F, 0x00]))  # Severity 3 (of 0..2), SpeedRpm 16383.5 rpm
    rec = w.take(0.2, 0x304, alert)
    assert "Severity 3 is not a defined value" in rec["suspect"]
    assert "SpeedRpm 16383.5 is outside its DBC range" in rec["suspect"]
    assert w.suspect == 2 and w.seen["OidStatus"].values["State"] == "TRACKING"  # the last good values stay
    assert w.seen["OidAlert"].count == 0 and not w.alerts


def test_random_frames_that_pass_the_crc_are_mostly_suspect():
    rng = np.random.default_rng(5)
    w = _watch()
    passed = shown = 0
    for data in rng.integers(0, 256, size=(40000, 8), dtype=np.uint8):
        head = bytes(data[:7])
        rec = w.take(0.0, 0x303, _with_crc(head))
        passed += 1
        if "signals" in rec:
            shown += 1
            assert isinstance(rec["signals"]["State"], str)  # a defined state, never a number
            assert isinstance(rec["signals"]["LastCommand"], str)
    assert passed == 40000 and w.suspect == passed - shown
    assert shown / passed < 0.02  # State 0..5 of 256 and LastCommand 0..3 of 16: 0.6 % pass both


def test_monitor_prints_suspect_frames(capsys):
    channel = f"suspect-{os.getpid()}"
    frames = [OutputEncoder(DB).encode(EstimateOut(1.0, 23.26, 0.0564, 5493.0, 4.24, True))[0],
              (0x303, _with_crc(bytes([238, 0, 0, 0, 0, 0, 0x10])))]

    def send():
        from can.interfaces.virtual import channels

        deadline = time.monotonic() + 10
        while not channels.get(channel) and time.monotonic() < deadline:
            time.sleep(0.01)
        with CanBus("virtual", channel) as bus:
            for ident, data in frames:
                bus.send(ident, data)

    sender = threading.Thread(target=send)
    sender.start()
    rc = main(["monitor", "--interface", "virtual", "--channel", channel, "--max-seconds", "1.0", "--json"])
    sender.join()
    docs = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert rc == 0 and len(docs) == 2
    assert "signals" in docs[0] and "suspect" in docs[1] and "signals" not in docs[1]
