"""MQTT telemetry against a real mosquitto on loopback (skipped, saying why, when mosquitto is absent)."""

import dataclasses
import io
import json
import math
import os
import shutil
import socket
import threading
import time

import pytest

pytest.importorskip("paho.mqtt.client", reason="paho-mqtt is not installed (pip install 'online-id[mqtt]')")
import paho.mqtt.client as paho  # noqa: E402

from mqtt_broker import EXE, MISSING, Mosquitto, make_ca, make_server_cert, wait_for  # noqa: E402
from online_id.bench.scenario import BenchScenario, OperatingPoint  # noqa: E402
from online_id.bench.simulate import simulate_bench  # noqa: E402
from online_id.cli import main  # noqa: E402
from online_id.config import BusSettings, MqttSettings, Settings, load_config  # noqa: E402
from online_id.errors import ConfigError  # noqa: E402
from online_id.io.bus import CanBus  # noqa: E402
from online_id.io.dbc import encode_inputs  # noqa: E402
from online_id.io.mqtt import MqttTelemetry, payload  # noqa: E402
from online_id.service.offload import InlineWorker  # noqa: E402
from online_id.records import AlertKind, AlertOut, EstimateOut, QualityOut, ServiceState, StatusOut  # noqa: E402
from online_id.service.live import Service  # noqa: E402

needs_broker = pytest.mark.skipif(EXE is None, reason=MISSING)


class Subscriber:
    """Everything under ``online-id/#``, QoS 1 on a persistent session (kept by the broker across its restart)."""

    def __init__(self, port: int, name: str = "test-subscriber", ca_file=None) -> None:
        self.messages: list[tuple[str, dict, bool]] = []
        self.subscribed = threading.Event()
        c = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=name, clean_session=False)
        if ca_file is not None:
            c.tls_set(ca_certs=str(ca_file))
        c.reconnect_delay_set(0.05, 0.2)
        c.on_connect = lambda cl, *_: cl.subscribe("online-id/#", qos=1)
        c.on_subscribe = lambda *_: self.subscribed.set()
        c.on_message = lambda cl, ud, m: self.messages.append((m.topic, json.loads(m.payload), bool(m.retain)))
        c.connect_async("127.0.0.1", port)
        c.loop_start()
        self.client = c
        assert self.subscribed.wait(10), "the test subscriber did not subscribe"

    def of(self, kind: str) -> list[dict]:
        return [p for t, p, _ in list(self.messages) if t.endswith("/" + kind)]

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def broker(tmp_path):
    if EXE is None:
        pytest.skip(MISSING)
    b = Mosquitto(tmp_path / "broker").start()
    yield b
    b.stop()


def mqtt_settings(port: int, **kw) -> MqttSettings:
    return MqttSettings(**({"host": "127.0.0.1", "port": port, "bench": "bench-1", "reconnect_max_s": 0.5} | kw))


# --- payloads -------------------------------------------------------------------------------------


def test_payloads_carry_units_and_nan_becomes_null():
    kind, est = payload(EstimateOut(1.5, 23.4, 0.05, math.nan, 3.0, True))
    assert kind == "estimate" and est["f0_hz"] == 23.4 and est["damping_ratio"] == 0.05
    assert est["shaft_stiffness_nm_per_rad"] is None and est["shaft_damping_nm_s_per_rad"] == 3.0
    json.dumps(est, allow_nan=False)
    kind, q = payload(QualityOut(1.5, 0.01, 4e-4, 12.0, 900))
    assert kind == "quality" and q["fpe_rms_rad_s"] == pytest.approx(0.02) and q["excitation_rms_nm"] == 12.0
    kind, a = payload(AlertOut(2.0, AlertKind.FREQ_DRIFT, 2, -3.5, 1500.0, "f0 down"))
    assert (kind, a["kind"], a["severity"], a["change_pct"], a["speed_rpm"]) == (
        "alert", "FREQ_DRIFT", "fault", -3.5, 1500.0)


def test_password_sources_and_their_errors(tmp_path, monkeypatch):
    from online_id.io.mqtt import resolve_password

    (tmp_path / "pw").write_text("s3cret\n")
    assert resolve_password(MqttSettings(username="u", password_file=str(tmp_path / "pw"))) == "s3cret"
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(tmp_path))  # systemd LoadCredential=
    assert resolve_password(MqttSettings(username="u", password_file="pw")) == "s3cret"
    monkeypatch.setenv("OID_PW", "from-env")
    assert resolve_password(MqttSettings(username="u", password_env="OID_PW")) == "from-env"
    with pytest.raises(ConfigError, match=r"^mqtt.password_file: cannot read .*nope"):
        resolve_password(MqttSettings(username="u", password_file=str(tmp_path / "nope")))
    with pytest.raises(ConfigError, match=r"^mqtt.password_env: environment variable OID_NONE is not set$"):
        resolve_password(MqttSettings(username="u", password_env="OID_NONE"))
    cfg = tmp_path / "c.yaml"
    cfg.write_text("mqtt:\n  host: b\n  password: x\n")
    with pytest.raises(ConfigError, match=r"c.yaml: mqtt.username: mqtt.password needs a user name"):
        load_config(cfg)


# --- the service on a simulated bench -------------------------------------------------------------


def bench_chunks(n: int, seconds: float):
    sc = dataclasses.replace(BenchScenario(), seed=3, operating_points=(OperatingPoint(1200.0, seconds),))
    rec = simulate_bench(sc)
    frames = encode_inputs(rec.time_s, rec.dyno_speed_rpm, rec.engine_speed_rpm, rec.dyno_torque_nm)
    size = math.ceil(len(frames) / n)
    return [frames[i:i + size] for i in range(0, len(frames), size)]


class BenchFeed:
    """The service on python-can's virtual bus, fed chunk by chunk; each chunk continues the stream clock."""

    def __init__(self, settings: Settings, log) -> None:
        channel = f"mqtt-{os.getpid()}-{id(self)}"
        self.svc = Service(dataclasses.replace(settings, bus=BusSettings(interface="virtual", channel=channel)),
                           bus_factory=lambda: CanBus("virtual", channel, preserve_timestamps=True), log=log,
                           worker=InlineWorker())
        self.sender = CanBus("virtual", channel, preserve_timestamps=True)
        self.rc: list[int] = []
        self.thread = threading.Thread(target=lambda: self.rc.append(self.svc.run(max_s=60)))
        self.thread.start()
        self.sent, self.shift, self.last_t = 0, None, None

    def send(self, chunk) -> None:
        if self.last_t is not None:  # the stream moved on with the wall clock while we waited
            self.shift = self.last_t + (time.monotonic() - self.done_wall) + 0.01 - chunk[0][0]
        self.shift = self.shift or 0.0
        for t, i, d in chunk:
            self.sender.send(i, d, t_s=t + self.shift)
        self.sent += len(chunk)
        self.last_t = chunk[-1][0] + self.shift
        assert wait_for(lambda: self.svc.runtime.frames_in >= self.sent, 30), "the service fell behind"
        self.done_wall = time.monotonic()

    def stop(self) -> int:
        self.svc.request_stop()
        self.thread.join(30)
        self.sender.close()
        return self.rc[0]


@needs_broker
def test_service_publishes_each_kind_and_a_broker_restart_loses_nothing(broker, tmp_path):
    sub = Subscriber(broker.port)
    log = io.StringIO()
    feed = BenchFeed(Settings(mqtt=mqtt_settings(broker.port)), log)
    tel = feed.svc.telemetry
    try:
        assert wait_for(lambda: tel.connected, 10)
        chunks = bench_chunks(3, 6.0)
        feed.send(chunks[0])
        assert wait_for(lambda: tel.idle() and tel.published > 0, 10)
        before = tel.enqueued
        broker.stop()
        assert wait_for(lambda: not tel.connected, 10)
        feed.send(chunks[1])  # published while the broker is away: buffered
        during = tel.enqueued - before
        assert during > 20 and tel.buffered > 0
        time.sleep(0.3)  # input silence: INPUT_TIMEOUT and its alert, still without a broker
        broker.start()
        assert wait_for(lambda: tel.connected, 10)
        feed.send(chunks[2])
        time.sleep(0.3)
        assert wait_for(lambda: tel.idle(), 10)
    finally:
        rc = feed.stop()
    assert rc == 0
    assert wait_for(lambda: any(p.get("state") == "STOPPED" for p in sub.of("status")), 10)
    sub.close()
    seqs = {p["seq"] for _, p, _ in sub.messages if "seq" in p}
    assert tel.dropped == 0 and seqs == set(range(1, tel.enqueued + 1))  # every message, in spite of the restart
    est = [p for p in sub.of("estimate")]
    assert est and all(p["bench"] == "bench-1" and "f0_hz" in p and "damping_ratio" in p for p in est)
    assert any(p["f0_hz"] is not None and 5 < p["f0_hz"] < 100 for p in est)
    assert sub.of("quality")[-1]["excitation_rms_nm"] > 0
    states = [p["state"] for p in sub.of("status")]
    assert {"LEARNING", "INPUT_TIMEOUT", "STOPPED"} <= set(states)
    alerts = sub.of("alert")
    assert any(a["kind"] == "INPUT_FAULT" and a["severity"] == "warning" for a in alerts)
    text = log.getvalue()
    assert "mqtt: lost broker" in text and text.count("mqtt: connected to") == 2


@needs_broker
def test_full_buffer_drops_the_oldest_and_counts_them(tmp_path):
    b = Mosquitto(tmp_path / "broker")  # not started yet: the broker is away from the beginning
    lines = []
    tel = MqttTelemetry(mqtt_settings(b.port, buffer_messages=5), lines.append)
    try:
        tel.publish([StatusOut(float(i), ServiceState.TRACKING, i, 0) for i in range(12)])
        assert (tel.enqueued, tel.dropped, tel.buffered) == (12, 7, 5)
        assert wait_for(lambda: tel.fault is not None, 5) and "cannot reach broker" in tel.fault
        b.start()
        sub = Subscriber(b.port)
        assert wait_for(lambda: tel.idle() and tel.published >= 5, 10)
        assert wait_for(lambda: len(sub.of("status")) >= 5, 5)
        got = sorted(p["seq"] for p in sub.of("status"))
        assert got == [8, 9, 10, 11, 12]  # the newest five; seq 1..7 were dropped
        assert sub.of("status")[-1]["telemetry_dropped_messages"] == 7
        sub.close()
    finally:
        tel.close("TRACKING", timeout_s=1.0)
        b.stop()
    assert lines[0].startswith("mqtt: cannot reach broker") and lines.count(lines[0]) == 1


@needs_broker
def test_last_will_marks_the_bench_offline(broker):
    sub = Subscriber(broker.port)
    tel = MqttTelemetry(mqtt_settings(broker.port, bench="bench-w", keepalive_s=5), lambda _t: None)
    try:
        assert wait_for(lambda: tel.connected, 10)
        tel.client.socket().shutdown(socket.SHUT_RDWR)  # the connection dies without a DISCONNECT
        assert wait_for(lambda: any(p.get("state") == "OFFLINE" for p in sub.of("status")), 10)
        will = [p for p in sub.of("status") if p.get("state") == "OFFLINE"][0]
        assert will == {"bench": "bench-w", "online": False, "state": "OFFLINE", "reason": "connection lost"}
    finally:
        tel.close("STARTING", timeout_s=0.5)
        sub.close()


@needs_broker
def test_wrong_password_is_one_clear_line_and_the_service_keeps_running(tmp_path):
    b = Mosquitto(tmp_path / "broker", users={"bench": "right"}).start()
    (tmp_path / "pw").write_text("wrong\n")
    log = io.StringIO()
    s = Settings(mqtt=mqtt_settings(b.port, username="bench", password_file=str(tmp_path / "pw")))
    feed = BenchFeed(s, log)
    try:
        tel = feed.svc.telemetry
        assert wait_for(lambda: tel.fault is not None, 10)
        feed.send(bench_chunks(4, 2.0)[0])
        assert feed.thread.is_alive() and feed.svc.runtime.frames_in > 0
        time.sleep(1.2)  # paho retries: the fault is said once, not on every retry
    finally:
        assert feed.stop() == 0
        b.stop()
    refused = [ln for ln in log.getvalue().splitlines() if "refused" in ln]
    assert len(refused) == 1, log.getvalue()
    assert refused[0] == (f"online-id: mqtt: broker 127.0.0.1:{b.port} refused the connection: Not authorized "
                          f"(check mqtt.username 'bench' and mqtt.password_file)")
    assert "Traceback" not in log.getvalue() and tel.published == 0 and tel.enqueued > 0


# --- online-id fleet ------------------------------------------------------------------------------


@needs_broker
@pytest.mark.skipif(shutil.which("openssl") is None, reason="the openssl command is not installed")
def test_tls_with_the_benchs_ca_publishes_and_an_untrusted_certificate_is_one_clear_line(tmp_path):
    """A TLS listener: the CA in mqtt.ca_file verifies it; another CA is refused, said once, the queue kept."""
    ca = make_ca(tmp_path / "pki")
    server = make_server_cert(tmp_path / "pki", ca)
    b = Mosquitto(tmp_path / "broker", tls=(ca[0], *server)).start()
    sub = Subscriber(b.port, ca_file=ca[0])
    logs: list[str] = []
    good = MqttTelemetry(mqtt_settings(b.port, bench="bench-tls", tls=True, ca_file=str(ca[0])), logs.append)
    other_ca = make_ca(tmp_path / "other", "other-ca")
    bad_logs: list[str] = []
    bad = MqttTelemetry(mqtt_settings(b.port, bench="bench-bad", tls=True, ca_file=str(other_ca[0])), bad_logs.append)
    try:
        good.publish([EstimateOut(3.0, 21.5, 0.04, 1.2e4, 2.0, True), StatusOut(3.0, ServiceState.TRACKING, 0, 0)])
        bad.publish([StatusOut(3.0, ServiceState.TRACKING, 0, 0)])
        assert wait_for(lambda: any(p.get("f0_hz") == 21.5 for p in sub.of("estimate")), 10), logs
        assert good.connected and good.fault is None
        assert wait_for(lambda: bad.fault is not None, 10)
        time.sleep(1.2)  # paho retries: said once
        assert not bad.connected and bad.published == 0 and bad.enqueued >= 1
        assert len(bad_logs) == 1 and "\n" not in bad_logs[0], bad_logs
        assert bad_logs[0].startswith(f"mqtt: broker 127.0.0.1:{b.port}: TLS certificate not trusted (")
        assert f"check mqtt.ca_file {str(other_ca[0])!r}" in bad_logs[0]
        assert not any(t.endswith("bench-bad/status") for t, _p, _r in sub.messages)
    finally:
        good.close("STOPPED", timeout_s=1.0)
        bad.close("STOPPED", timeout_s=0.2)
        sub.close()
        b.stop()


@needs_broker
def test_fleet_once_shows_every_bench_with_estimate_state_and_alert(broker, capsys):
    sinks = [MqttTelemetry(mqtt_settings(broker.port, bench=name), lambda _t: None) for name in ("bench-a", "bench-b")]
    try:
        a, b = sinks
        a.publish([EstimateOut(1.0, 23.41, 0.052, 12000.0, 3.1, True), QualityOut(1.0, 0.004, 2.5e-5, 14.2, 800),
                   AlertOut(1.0, AlertKind.FREQ_DRIFT, 2, -3.2, 1500.0, "f0 down 3.2 %"),
                   StatusOut(1.0, ServiceState.TRACKING, 0, 0)])
        b.publish([EstimateOut(1.0, 31.0, 0.08, math.nan, math.nan, False), StatusOut(1.0, ServiceState.LEARNING, 2, 0)])
        assert wait_for(lambda: all(s.idle() and s.published >= 2 for s in sinks), 10)
        capsys.readouterr()
        assert main(["fleet", "--broker", f"127.0.0.1:{broker.port}", "--once"]) == 0
        out = capsys.readouterr().out
    finally:
        for s in sinks:
            s.close("TRACKING", timeout_s=1.0)
    lines = out.splitlines()
    assert "f0 [Hz]" in lines[0] and "zeta [-]" in lines[0]
    row_a = next(ln for ln in lines if ln.startswith("bench-a"))
    row_b = next(ln for ln in lines if ln.startswith("bench-b"))
    assert "TRACKING" in row_a and "23.41" in row_a and "0.052" in row_a and "FREQ_DRIFT" in row_a
    assert "LEARNING" in row_b and "31.00" not in row_b  # an invalid estimate is not shown as a value


def test_fleet_says_in_one_line_when_the_broker_is_not_there(cli_error):
    from mqtt_broker import free_port

    err = cli_error(["fleet", "--broker", f"127.0.0.1:{free_port()}", "--once", "--wait", "1"])
    assert "cannot reach broker 127.0.0.1" in err


def test_the_example_mqtt_section_of_deploy_config_is_valid(tmp_path):
    from pathlib import Path

    text = (Path(__file__).parent.parent / "deploy" / "config.yaml").read_text()
    block = text[text.index("# mqtt:"):].splitlines()
    cfg = tmp_path / "c.yaml"
    cfg.write_text("\n".join(line.replace("# ", "", 1) for line in block if line.startswith("#")) + "\n")
    m = load_config(cfg).mqtt
    assert (m.host, m.port, m.bench, m.tls, m.password_file) == (
        "broker.plant.local", 8883, "bench-07", True, "mqtt-password")
