"""Conventions of the neighbouring tools: -i/-c/-b as python-can's, units in monitor, fleet columns to content."""

import argparse
import json

import pytest

from online_id.cli.bus_options import with_bus_options
from online_id.config import Settings


@pytest.mark.parametrize("command", ["run", "monitor", "ack", "relearn"])
def test_short_bus_options_as_python_can_tools(command):
    from online_id.cli import build_parser

    args = build_parser(command).parse_args([command, "-i", "virtual", "-c", "bench7", "-b", "500000"])
    s = with_bus_options(Settings(), args)
    assert (s.bus.interface, s.bus.channel, s.bus.bitrate) == ("virtual", "bench7", 500000)
    long = build_parser(command).parse_args([command, "--interface", "virtual", "--channel", "x", "--bitrate", "250000"])
    assert with_bus_options(Settings(), long).bus.bitrate == 250000


def test_bad_bitrate_is_one_line(cli_error):
    assert "--bitrate" in cli_error(["monitor", "-i", "virtual", "-c", "x", "-b", "0", "--max-seconds", "0.1"])


def test_monitor_shows_units_from_the_dbc():
    from online_id.cli.monitor import line, open_watch, screen
    from online_id.io.dbc_output import OutputEncoder
    from online_id.io.dbc import load_dbc
    from online_id.records import EstimateOut

    args = argparse.Namespace(config=None, interface="virtual", channel="x", bitrate=None)
    _, watch, interface, channel = open_watch(args)
    assert (interface, channel) == ("virtual", "x")
    enc = OutputEncoder(load_dbc())
    (fid, data), *_ = enc.encode(EstimateOut(1.0, 24.98, 0.052, 6000.0, 4.0, True))
    record = watch.take(1.0, fid, data)
    text = line(record)
    assert "ResonanceFreq 24.98 Hz" in text
    assert json.loads(json.dumps(record))["units"]["ResonanceFreq"] == "Hz"
    assert "24.98 Hz" in screen(watch, 1.5, "virtual:x")


def test_fleet_columns_fit_their_content_and_the_last_alert_is_whole():
    from online_id.cli.fleet import Fleet

    fleet = Fleet("online-id")
    long_name = "engine-test-bench-number-twelve"
    message = "driveline frequency down 7.2 % against the baseline of 1375-1625 rpm (fault, latched)"
    fleet.update(f"online-id/{long_name}/status", json.dumps({"state": "TRACKING", "alerts_total": 3,
                                                             "time_unix_s": 100.0}).encode())
    fleet.update(f"online-id/{long_name}/alert", json.dumps({"kind": "FREQ_DRIFT", "severity": 2,
                                                            "message": message}).encode())
    fleet.update("online-id/b2/estimate", json.dumps({"valid": True, "f0_hz": 24.98, "damping_ratio": 0.052,
                                                      "shaft_stiffness_nm_per_rad": 123456789.0}).encode())
    lines = fleet.table(101.0).splitlines()
    assert any(long_name in ln and ln.endswith(message) for ln in lines)  # neither cut
    assert any("123456789" in ln for ln in lines)
    head, b2, bench = lines[0], next(ln for ln in lines if ln.startswith("b2 ")), next(
        ln for ln in lines if ln.startswith(long_name))
    assert head.index("STATE") == bench.index("TRACKING") == b2.index("?")  # the columns line up
    assert head.index("f0 [Hz]") + len("f0 [Hz]") == b2.index("24.98") + len("24.98")  # numbers to the right
    assert len(fleet.table(101.0, width=60).splitlines()[1]) <= 60  # a terminal's width cuts the last column only
