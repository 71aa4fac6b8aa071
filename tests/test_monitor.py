"""`online-id monitor`, the service's answer to `ack`/`relearn`, replay of a log without configured IDs, progress."""

import io
import json
import os
import threading
import time

import pytest

from online_id.cli import main
from online_id.io.bus import CanBus
from online_id.io.canlog import write_log
from online_id.io.dbc_output import OutputEncoder
from online_id.progress import Progress
from online_id.records import AlertKind, AlertOut, EstimateOut, ServiceState, StatusOut


def _service(channel, stop, config=None):
    """A stand-in for the service: the runtime of the live service answering on a virtual bus."""
    from online_id.config import load_config
    from online_id.service.runtime import Runtime

    runtime = Runtime(load_config(config))
    with CanBus("virtual", channel) as bus:
        while not stop.is_set():
            f = bus.recv(0.05)
            if f is not None:
                for ident, data in runtime.on_frame(time.monotonic(), f.arbitration_id, f.data):
                    bus.send(ident, data)


def test_ack_and_relearn_report_what_the_service_did(tmp_path, capsys):
    channel = f"answer-{os.getpid()}"
    cfg = tmp_path / "strict.yaml"
    cfg.write_text("commands:\n  relearn: disabled\n")
    for config, relearn_rc, relearn_says in ((None, 0, "RELEARN_BASELINE ACCEPTED"),
                                             (cfg, 1, "RELEARN_BASELINE REFUSED (state STARTING); its log says")):
        stop = threading.Event()
        thread = threading.Thread(target=_service, args=(channel, stop, config))
        thread.start()
        try:
            from can.interfaces.virtual import channels  # python-can's in-process virtual buses

            deadline = time.monotonic() + 10
            while not channels.get(channel) and time.monotonic() < deadline:  # until the service listens
                time.sleep(0.01)
            assert main(["ack", "--interface", "virtual", "--channel", channel]) == 0
            assert "service answered: ACK_ALERT ACCEPTED (state STARTING)" in capsys.readouterr().out
            assert main(["relearn", "--interface", "virtual", "--channel", channel]) == relearn_rc
            assert f"service answered: {relearn_says}" in capsys.readouterr().out
        finally:
            stop.set()
            thread.join()
    assert main(["ack", "--interface", "virtual", "--channel", channel, "--wait", "0.3"]) == 1
    assert "no answer from the service within 0.3 s" in capsys.readouterr().out


def _send_outputs(channel):
    enc = OutputEncoder()
    pubs = [StatusOut(1.0, ServiceState.TRACKING, 2, 0), EstimateOut(1.0, 23.26, 0.0564, 5493.0, 4.24, True),
            AlertOut(1.1, AlertKind.FREQ_DRIFT, 1, -5.2, 1400.0, "f0 down")]
    frames = [f for p in pubs for f in enc.encode(p)]
    frames.append((0x303, bytes(8)))  # a status frame with a bad CRC
    from can.interfaces.virtual import channels  # python-can's in-process virtual buses

    deadline = time.monotonic() + 10
    while not channels.get(channel) and time.monotonic() < deadline:  # until the monitor listens
        time.sleep(0.01)
    with CanBus("virtual", channel) as bus:
        for ident, data in frames:
            bus.send(ident, data)


@pytest.mark.parametrize("as_json", [True, False])
def test_monitor_decodes_and_checks_the_output_frames(capsys, as_json):
    channel = f"monitor-{os.getpid()}-{as_json}"
    sender = threading.Thread(target=_send_outputs, args=(channel,))
    sender.start()
    rc = main(["monitor", "--interface", "virtual", "--channel", channel, "--max-seconds", "1.2",
               *(["--json"] if as_json else [])])
    sender.join()
    assert rc == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 5
    if as_json:
        docs = [json.loads(x) for x in lines]
        assert docs[0]["message"] == "OidStatus" and docs[0]["signals"]["State"] == "TRACKING"
        assert docs[1]["signals"]["ResonanceFreq"] == pytest.approx(23.26, abs=0.002)
        assert docs[3]["signals"]["AlertKind"] == "FREQ_DRIFT" and docs[3]["signals"]["DriftPct"] == -5.2
        assert docs[4]["error"].startswith("bad CRC")
    else:
        assert "0x300 OidEstimate  ResonanceFreq 23.26 Hz  DampingRatio 0.0564  Valid VALID" in lines[1]  # DBC units
        assert lines[4].endswith("OidStatus: bad CRC or length: data 0000000000000000")


def test_monitor_says_when_nothing_arrives(capsys):
    assert main(["monitor", "--interface", "virtual", "--channel", f"silent-{os.getpid()}",
                 "--max-seconds", "0.3"]) == 1
    assert "no output frame of the service in 0.3 s" in capsys.readouterr().err


def test_replay_of_a_log_without_configured_ids_fails(tmp_path, cli_error):
    log = tmp_path / "foreign.blf"
    write_log(log, [(0.001 * k, 0x7FF if k % 2 else 0x18FF0001, bytes(8)) for k in range(300)])
    err = cli_error(["replay", str(log)])
    assert "foreign.blf: none of its 300 frames has an ID the config maps (0x101, 0x102, 0x103, 0x120" in err
    assert err.endswith("the log holds IDs 0x7FF, 0x18FF0001")


def test_progress_shows_rate_and_time_left_only_on_a_terminal():
    now = [0.0]
    out = io.StringIO()
    p = Progress("replay", out, enabled=True, unit="frames", clock=lambda: now[0])
    now[0] = 10.0
    p.count(25_000, 100_000, "t = 5.0 s")
    assert "replay [#####---------------]  25.0%   10.0 s  2,500 frames/s  30 s left  t = 5.0 s" in out.getvalue()
    p.close()
    assert out.getvalue().endswith("\r")
    quiet = io.StringIO()
    for q in (Progress("x", quiet, enabled=True, quiet=True), Progress("x", quiet)):  # --json; not a terminal
        q(0.5)
        q.close()
    assert quiet.getvalue() == ""
