"""The streaming service: frames in, frames out, on python-can's virtual bus and from logs."""

import dataclasses
import hashlib
import io
import json
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.cli import main
from online_id.config import BusSettings, ExcitationSettings, Settings, StateSettings
from online_id.errors import BusError
from online_id.io.bus import CanBus
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.service.offload import InlineWorker
from online_id.service.reaction import read_summaries
from online_id.records import FrameFault, ServiceState
from online_id.service.runtime import Runtime
from online_id.service.live import Service

DB = load_dbc(None)
ENC = OutputEncoder(DB)
OUT_IDS = {0x300, 0x301, 0x302, 0x303, 0x304, 0x305}


def bench_frames(seconds=12.0, seed=1, speeds=(1200.0,)):
    sc = dataclasses.replace(BenchScenario(), seed=seed,
                             operating_points=tuple(OperatingPoint(s, seconds / len(speeds)) for s in speeds))
    rec = simulate_bench(sc)
    return rec, encode_inputs(rec.time_s, rec.dyno_speed_rpm, rec.engine_speed_rpm, rec.dyno_torque_nm, db=DB)


def statuses(frames):
    return [ENC.decode(i, d) for i, d in frames if i == 0x303]


# --- end to end on the virtual bus ------------------------------------------------------------


def test_service_on_virtual_bus_end_to_end(tmp_path):
    rec, frames = bench_frames(8.0)
    channel = f"test-e2e-{os.getpid()}"
    settings = Settings(bus=BusSettings(interface="virtual", channel=channel),
                        state=StateSettings(directory=str(tmp_path)))
    log = io.StringIO()
    svc = Service(settings, bus_factory=lambda: CanBus("virtual", channel, preserve_timestamps=True), log=log)
    consumer = CanBus("virtual", channel)
    sender = CanBus("virtual", channel, preserve_timestamps=True)
    status = {}
    th = threading.Thread(target=lambda: status.setdefault("rc", svc.run(max_s=60)))
    th.start()
    time.sleep(0.3)
    for t, i, d in frames:
        sender.send(i, d, t_s=t)
    # wait until the service has consumed everything, then stop it like SIGTERM would
    deadline = time.monotonic() + 60
    while svc.runtime.frames_in < len(frames) and time.monotonic() < deadline:
        time.sleep(0.05)
    svc.request_stop()
    th.join(20)
    out = []
    while (f := consumer.recv(0.05)) is not None:
        if f.arbitration_id in OUT_IDS:
            out.append((f.arbitration_id, f.data))
    sender.close()
    consumer.close()
    assert status["rc"] == 0
    assert svc.runtime.frames_in == len(frames)
    assert out and all(ENC.verify(i, d) for i, d in out)  # every published frame passes its CRC
    states = [ServiceState(int(s["State"])) for s in statuses(out)]
    assert states[0] == ServiceState.LEARNING
    assert {i for i, _ in out} >= {0x300, 0x301, 0x302, 0x303}
    counters = [ENC.decode(i, d)["OidEstimateCounter"] for i, d in out if i == 0x300]
    assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:]))  # alive counter steps by one
    assert (tmp_path / "online-id-state.json").exists()  # state saved on stop
    # each OidEstimate is sent first, before the rest of its publication was made, and the rest follows in order
    ids = [i for i, _ in out]
    assert all(ids[k + 1:k + 4] == [0x301, 0x302, 0x303] for k, i in enumerate(ids) if i == 0x300)
    # the loop measured its own work on every frame that published, in wall and CPU time and by phase (the frames'
    # stamps are the simulation's, so the wait before the loop is not measurable here)
    n = len(counters)
    text = log.getvalue()
    assert f"over {n} outputs; its CPU time: processing CPU p50" in text and text.count(f"over {n} outputs") == 5
    phases = next(ln for ln in text.splitlines() if "the loop on a frame that publishes, by phase" in ln)
    assert "pipeline CPU p50" in phases and "encoding CPU p50" in phases and "sending CPU p50" in phases
    assert "waiting time not measured" in phases
    # ... as benchmarks/bench_live reads them: every figure of every measured one, in order, the whole loop's CPU
    # time at least its phases' (each histogram's bins are 10 us: p50 rounds up to a bin's upper edge)
    figures = read_summaries(text)
    assert sorted(figures) == ["encoding CPU", "pipeline CPU", "processing", "processing CPU", "sending CPU"]
    assert all(f["n"] == n and 0 <= f["p50"] <= f["p99"] <= f["max"] for f in figures.values())
    cpu = figures["processing CPU"]
    assert cpu["max"] >= max(figures[w]["max"] for w in ("pipeline CPU", "encoding CPU", "sending CPU")) - 1e-9


# --- replay = offline recursive identification, within 1 % of the truth ---------------------------


_RECURSIVE: dict[str, dict] = {}  # identify --recursive --json of a CSV, by its content


def _identify_recursive(csv, capsys) -> dict:
    """``online-id identify CSV --recursive --json``, once per content of the CSV (the .log and .blf cases below
    simulate the same bench)."""
    key = hashlib.sha256(csv.read_bytes()).hexdigest()
    if key not in _RECURSIVE:
        capsys.readouterr()
        assert main(["identify", str(csv), "--recursive", "--json"]) == 0
        _RECURSIVE[key] = json.loads(capsys.readouterr().out)
    return _RECURSIVE[key]


@pytest.mark.slow
@pytest.mark.parametrize("plant,suffix", [({}, ".log"), ({}, ".blf"),
                                          ({"J1": 1.1, "J2": 0.3, "c_s": 9000.0, "d_s": 5.0}, ".log")])
def test_replay_matches_identify_recursive_and_truth(tmp_path, capsys, plant, suffix):
    cfg = tmp_path / "scenario.yaml"
    # two points of 25 s (the default bench holds four of 40 s): valid from about 10 s into each
    points = [{"speed_rpm": 1300.0, "duration_s": 25.0}, {"speed_rpm": 2000.0, "duration_s": 25.0}]
    cfg.write_text(json.dumps({"seed": 11, "operating_points": points, **plant}))
    csv, log = tmp_path / "bench.csv", tmp_path / f"bench{suffix}"
    assert main(["simulate", "--config", str(cfg), "--out", str(csv), "--can-log", str(log)]) == 0
    truth = json.loads(csv.with_suffix(".truth.json").read_text())
    capsys.readouterr()
    assert main(["replay", str(log), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    off = _identify_recursive(csv, capsys)
    for key in ("f0_hz", "zeta", "c_s", "d_s"):
        assert rep["driveline"][key] == pytest.approx(off["driveline"][key], rel=1e-9), key
    assert rep["driveline"]["f0_hz"] == pytest.approx(truth["f0_hz"], rel=0.01)
    assert rep["driveline"]["zeta"] == pytest.approx(truth["zeta"], rel=0.15)
    assert rep["state"] == "TRACKING" and rep["driveline"]["valid"]
    assert [c["state"] for c in rep["status_changes"]][:2] == ["LEARNING", "TRACKING"]
    assert rep["status_changes"][0]["t_s"] == pytest.approx(0.0, abs=0.01)
    assert rep["alerts"] == []


# --- bad input: the service never stops, counts each kind and reports it ------------------------------


def test_bad_frames_are_counted_and_reported():
    rec, frames = bench_frames(4.0)
    rng = random.Random(5)
    bad = []
    for t, i, d in frames[::40]:
        kind = rng.randrange(4)
        if kind == 0:
            bad.append((t, rng.choice([0x7FF, 0x1, 0x555, 0x300]), bytes(rng.randrange(256) for _ in range(8))))
        elif kind == 1:
            bad.append((t, i, d[:5]))  # wrong DLC
        elif kind == 2:
            bad.append((t, 0x101, (2**31 - 1).to_bytes(4, "little", signed=True) + bytes(4)))  # out of range
        else:
            bad.append((t, 0x120, bytes([200, 0])))  # undefined command value
    stream = sorted(frames + bad, key=lambda f: f[0])
    rt = Runtime(Settings())
    out = []
    for t, i, d in stream:
        out += rt.on_frame(t, i, d)
    c = rt.pipeline.counters
    assert c.faults[FrameFault.UNKNOWN_ID] > 0
    assert c.faults[FrameFault.BAD_DLC] > 0
    assert c.faults[FrameFault.OUT_OF_RANGE] > 0
    assert c.samples >= 0.98 * len(rec.time_s)  # good frames still assembled
    last = statuses(out)[-1]  # published at most one publish period before the end
    assert 0.9 * c.bad_frames <= last["BadFrames"] <= c.bad_frames
    # a flood of foreign frames and a silence: no crash, timeout reported, clean resume
    t_end = stream[-1][0]
    for k in range(20000):
        rt.on_frame(t_end + k * 1e-6, 0x7E0, bytes(8))
    out = rt.tick(t_end + 1.0)
    assert rt.pipeline.state == ServiceState.INPUT_TIMEOUT
    assert any(s["State"] == ServiceState.INPUT_TIMEOUT for s in statuses(out))
    alerts = [ENC.decode(i, d) for i, d in out if i == 0x304]
    assert alerts and int(alerts[0]["AlertKind"]) == 4  # INPUT_FAULT
    later = [(t + t_end + 2.0, i, d) for t, i, d in bench_frames(2.0, seed=2)[1]]
    out = []
    for t, i, d in later:
        out += rt.on_frame(t, i, d)
    assert rt.pipeline.state != ServiceState.INPUT_TIMEOUT
    assert rt.pipeline.counters.gaps >= 1


def test_error_frames_and_garbage_never_raise():
    rt = Runtime(Settings())
    rng = np.random.default_rng(9)
    for k in range(5000):
        ident = int(rng.choice([0x101, 0x102, 0x103, 0x120, int(rng.integers(0, 0x800))]))
        data = bytes(rng.integers(0, 256, int(rng.integers(0, 9))).tolist())
        rt.on_frame(k * 1e-4 - (0.5 if rng.random() < 0.01 else 0.0), ident, data, is_error=rng.random() < 0.01)
    assert rt.frames_in == 5000


# --- state persistence -------------------------------------------------------------------------------


def test_restart_restores_estimator_state(tmp_path):
    rec, frames = bench_frames(6.0)
    settings = Settings(state=StateSettings(directory=str(tmp_path)))
    # the restore is the subject: inline workers (no child processes to spawn, warm up and leave behind)
    a = Service(settings, bus_factory=None, log=open(os.devnull, "w"), worker=InlineWorker())
    for t, i, d in frames:
        a.runtime.on_frame(t, i, d)
    a.save(final=True)  # here and now (a periodic save goes to the worker process)
    b = Service(settings, log=open(os.devnull, "w"), worker=InlineWorker())
    ta, tb = a.runtime.pipeline.estimator.rels.theta, b.runtime.pipeline.estimator.rels.theta
    assert np.array_equal(ta, tb) and np.any(ta != 0)
    # a corrupt state file is reported and ignored, never fatal
    (tmp_path / "online-id-state.json").write_text("{not json")
    log = tmp_path / "log.txt"
    with open(log, "w") as fh:
        c = Service(settings, log=fh, worker=InlineWorker())
    assert "ignoring saved state" in log.read_text()
    assert not np.any(c.runtime.pipeline.estimator.rels.theta)


# --- the process: signals, notify, bus down ----------------------------------------------------------


def test_sigterm_stops_cleanly_and_saves_state(tmp_path):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("bus: {interface: virtual, channel: sigterm-test}\n")
    env = dict(os.environ, STATE_DIRECTORY=str(tmp_path / "state"), PYTHONUNBUFFERED="1")
    sock_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.settimeout(30)
    env["NOTIFY_SOCKET"] = str(sock_path)
    proc = subprocess.Popen([sys.executable, "-m", "online_id", "run", "--config", str(cfg)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        msg = sock.recv(4096).decode()
        assert msg.startswith("READY=1")
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill() if proc.poll() is None else None
        sock.close()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "stopped" in err
    assert (tmp_path / "state" / "online-id-state.json").exists()


def test_watchdog_only_while_frames_flow(tmp_path, monkeypatch):
    sock_path = tmp_path / "n.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(sock_path))
    monkeypatch.setenv("WATCHDOG_USEC", "300000")  # ping every 0.1 s
    channel = f"wd-{os.getpid()}"
    svc = Service(Settings(bus=BusSettings(interface="virtual", channel=channel)),
                  bus_factory=lambda: CanBus("virtual", channel, preserve_timestamps=True), log=open(os.devnull, "w"))
    sender = CanBus("virtual", channel, preserve_timestamps=True)
    th = threading.Thread(target=svc.run, kwargs={"max_s": 30})
    th.start()
    _, frames = bench_frames(2.0)

    def drain():
        msgs = []
        while True:
            try:
                msgs.append(sock.recv(4096).decode())
            except BlockingIOError:
                return msgs

    time.sleep(1.5)
    silent = drain()
    t0 = time.monotonic()
    for t, i, d in frames:  # 2 s of bench, sent over about 1.5 s
        sender.send(i, d, t_s=t)
        if len(frames) and i == 0x103:
            while time.monotonic() - t0 < 0.75 * t:
                time.sleep(0.001)
    flowing = drain()
    time.sleep(0.5)  # the input timeout (0.2 s) passes: frames no longer flow
    drain()
    time.sleep(1.5)
    after = drain()
    svc.request_stop()
    th.join(20)
    sender.close()
    sock.close()
    assert any(m.startswith("READY=1") for m in silent)
    assert not any("WATCHDOG=1" in m for m in silent)
    assert sum("WATCHDOG=1" in m for m in flowing) >= 3
    assert not any("WATCHDOG=1" in m for m in after)


def test_bus_that_stays_down_ends_with_status_1(tmp_path):
    def broken():
        raise BusError("cannot open CAN bus socketcan:can9: No such device")

    settings = Settings(bus=BusSettings(reopen_max_s=0.5))
    log = tmp_path / "log.txt"
    with open(log, "w") as fh:
        svc = Service(settings, bus_factory=broken, log=fh, worker=InlineWorker())
        t0 = time.monotonic()
        assert svc.run() == 1
    assert time.monotonic() - t0 < 5
    assert "retrying" in log.read_text()


def test_run_command_reports_bad_config_in_one_line(tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("model: {forgeting: 0.99}\n")
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert "model.forgeting" in err and "\n" not in err


# --- excitation -------------------------------------------------------------------------------------


def test_excitation_only_when_healthy_and_in_window_and_stops_on_timeout():
    settings = Settings(excitation=ExcitationSettings(enabled=True, amplitude_nm=15.0, speed_window_rpm=(900, 1500)))
    rt = Runtime(settings)
    rec, frames = bench_frames(3.0, speeds=(1200.0,))
    out = []
    for t, i, d in frames:
        out += rt.on_frame(t, i, d)
    exc = [ENC.decode(i, d) for i, d in out if i == 0x305]
    assert exc and all(abs(abs(e["TorqueOffset"]) - 15.0) < 0.01 for e in exc if e["Active"])
    assert len({round(e["TorqueOffset"], 2) for e in exc}) == 2  # binary signal: +-amplitude
    out = rt.tick(frames[-1][0] + 1.0)  # inputs go silent
    exc = [ENC.decode(i, d) for i, d in out if i == 0x305]
    assert exc and exc[-1]["Active"] == 0 and exc[-1]["TorqueOffset"] == 0
    # outside the speed window nothing is requested
    rt2 = Runtime(settings)
    out = []
    for t, i, d in bench_frames(3.0, speeds=(2000.0,))[1]:
        out += rt2.on_frame(t, i, d)
    assert not [1 for i, d in out if i == 0x305 and ENC.decode(i, d)["Active"]]


def test_excitation_is_off_by_default():
    rt = Runtime(Settings())
    out = []
    for t, i, d in bench_frames(2.0)[1]:
        out += rt.on_frame(t, i, d)
    assert not [1 for i, _ in out if i == 0x305]
