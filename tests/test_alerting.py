"""Alerts leave the service as structured journal entries and through the command hook."""

import os
import socket
import time

from online_id.config import AlertSettings, Settings
from online_id.io.journal import Journal, encode_entry
from online_id.records import AlertKind, AlertOut
from online_id.service.offload import InlineWorker
from online_id.service.live import Service


def parse(datagram: bytes) -> dict:
    return dict(line.split("=", 1) for line in datagram.decode().splitlines())


def test_journal_entry_fields(tmp_path):
    path = tmp_path / "journal.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    j = Journal(str(path))
    assert j.enabled and j.send("stiffness about 12 % lower", priority=2, FAULT_CODE="FREQ_DRIFT", FREQ_DRIFT_PCT="-6.1")
    fields = parse(sock.recv(65536))
    assert fields == {"MESSAGE": "stiffness about 12 % lower", "PRIORITY": "2", "SYSLOG_IDENTIFIER": "online-id",
                      "FAULT_CODE": "FREQ_DRIFT", "FREQ_DRIFT_PCT": "-6.1"}
    sock.close()


def test_journal_multiline_values_use_the_binary_form():
    data = encode_entry({"MESSAGE": "a\nb"})
    assert data == b"MESSAGE\n" + (3).to_bytes(8, "little") + b"a\nb\n"


def test_missing_journal_is_a_no_op(tmp_path):
    assert not Journal(str(tmp_path / "none")).send("x")


def test_alert_goes_to_journal_and_hook(tmp_path, monkeypatch):
    jpath = tmp_path / "journal.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(jpath))
    monkeypatch.setattr("online_id.service.live.Journal", lambda: Journal(str(jpath)))
    out = tmp_path / "hook.txt"
    hook = tmp_path / "hook.sh"
    hook.write_text(f'#!/bin/sh\nenv | grep ^ONLINE_ID_ | sort > "{out}"\n')
    hook.chmod(0o755)
    svc = Service(Settings(alerts=AlertSettings(command=str(hook))), log=open(os.devnull, "w"), worker=InlineWorker())
    alert = AlertOut(12.5, AlertKind.FREQ_DRIFT, 2, -5.2, 1500.0,
                     "driveline frequency 5.2 % lower (stiffness about 10 % lower) since t = 10.0 s at 1500 rpm")
    svc._dispatch_alert(alert)
    fields = parse(sock.recv(65536))
    assert fields["FAULT_CODE"] == "FREQ_DRIFT" and fields["FREQ_DRIFT_PCT"] == "-5.20"
    assert fields["PRIORITY"] == "2" and fields["SPEED_RPM"] == "1500"
    deadline = time.monotonic() + 10
    while not (out.exists() and out.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    env = out.read_text()
    assert "ONLINE_ID_FAULT_CODE=FREQ_DRIFT" in env and "ONLINE_ID_FREQ_DRIFT_PCT=-5.20" in env
    assert "stiffness about 10 % lower" in env
    sock.close()


def test_ack_and_relearn_send_the_command_frame(capsys):
    import threading

    from online_id.cli import main
    from online_id.io.bus import CanBus
    from online_id.io.dbc import BenchCommand, InputDecoder, load_dbc
    from online_id.service.runtime import Runtime

    channel = f"ack-{os.getpid()}"
    dec = InputDecoder(load_dbc(None))
    runtime = Runtime(Settings())  # answers the senders' requests for the freshness value
    frames, stop, ready = [], threading.Event(), threading.Event()

    def listen():
        with CanBus("virtual", channel) as bus:
            ready.set()
            while not stop.is_set():
                f = bus.recv(0.05)
                if f is not None and f.arbitration_id == 0x120 and f.data[0]:
                    frames.append(f)
                elif f is not None:
                    for ident, data in runtime.on_frame(time.time(), f.arbitration_id, f.data):
                        bus.send(ident, data)

    thread = threading.Thread(target=listen)
    thread.start()
    try:
        assert ready.wait(10)
        for name in ("ack", "relearn"):
            assert main([name, "--interface", "virtual", "--channel", channel, "--wait", "0"]) == 0
        time.sleep(0.3)
    finally:
        stop.set()
        thread.join()
    # relearn sends the frame twice (confirmation), with consecutive freshness values; CRC checked
    out = [dec.decode(f.arbitration_id, f.data, 10.0) for f in frames]
    assert [o.command for o in out] == [BenchCommand.ACK_ALERT] + [BenchCommand.RELEARN_BASELINE] * 2
    assert out[2].freshness == out[1].freshness + 1
    assert "sent RELEARN_BASELINE" in capsys.readouterr().out