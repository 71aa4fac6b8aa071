"""MQTT telemetry: the service's publications as JSON on a topic tree per bench (paho-mqtt).

Topic tree (``<prefix>`` is ``mqtt.topic_prefix``, default ``online-id``;
``<bench>`` is ``mqtt.bench``, default the host name)::

    <prefix>/<bench>/estimate   retained  f0, damping ratio, shaft stiffness and damping
    <prefix>/<bench>/quality    retained  residual, FPE, excitation, samples used
    <prefix>/<bench>/status     retained  state, counters, alerts so far; the last will (offline)
    <prefix>/<bench>/alert      QoS >= 1  each alert as it is raised (not retained)

Payloads are JSON objects whose keys carry their unit (``f0_hz``,
``excitation_rms_nm``; NaN becomes ``null``); every payload has ``bench``,
``seq`` (one counter over all of this bench's messages since the service
started: a subscriber sees a gap as lost messages) and ``time_unix_s`` (wall
clock when the sample was published).

The receive loop never waits for the broker: :meth:`MqttTelemetry.publish`
only appends the publications to a bounded deque (when full, the oldest
message is dropped and counted). A sender thread takes them from there while
the broker is connected, encodes them and hands them to paho, whose network
thread writes them; at most :data:`IN_FLIGHT` messages are with paho and not
yet acknowledged at a time, and paho sends those again after a reconnect. So
while the broker is away, up to ``mqtt.buffer_messages`` messages wait and
nothing within that bound is lost (with QoS >= 1).
"""

from __future__ import annotations

import json
import math
import os
import socket
import ssl
import sys
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Callable, Iterable

from online_id.errors import ConfigError, OnlineIdError
from online_id.io.auth import credential_path
from online_id.records import AlertOut, EstimateOut, QualityOut, StatusOut

if TYPE_CHECKING:  # the settings are built by online_id.config (io does not import it)
    from online_id.config import MqttSettings

KINDS = ("estimate", "quality", "status", "alert")
IN_FLIGHT = 100  # messages handed to paho and not yet acknowledged, at most
POLL_S = 0.02  # the sender thread looks at the buffer at least this often
SEVERITY = {0: "info", 1: "warning", 2: "fault"}
AUTH_CODES = {4, 5, 134, 135}  # MQTT 3.1.1 bad user name or password / not authorized, and MQTT 5's


def _client_module():
    try:
        import paho.mqtt.client as mqtt
    except ImportError:
        raise ConfigError("mqtt.host is set but paho-mqtt is not installed "
                          "(pip install 'online-id[mqtt]')") from None
    return mqtt


def _num(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def resolve_password(s: MqttSettings) -> str | None:
    """The password from ``mqtt.password_file``, ``mqtt.password_env`` or ``mqtt.password``."""
    if s.password_file is not None:
        path = credential_path(s.password_file)
        try:
            return path.read_text(encoding="utf-8").rstrip("\r\n")
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"mqtt.password_file: cannot read {path}: "
                              f"{getattr(err, 'strerror', None) or err}") from None
    if s.password_env is not None:
        value = os.environ.get(s.password_env)
        if value is None:
            raise ConfigError(f"mqtt.password_env: environment variable {s.password_env} is not set")
        return value
    return s.password


def bench_name(s: MqttSettings) -> str:
    return s.bench or socket.gethostname().split(".")[0] or "bench"


def payload(pub: EstimateOut | QualityOut | StatusOut | AlertOut) -> tuple[str, dict]:
    """``(kind, fields)`` of one publication, units in the keys (see module notes)."""
    if isinstance(pub, EstimateOut):
        return "estimate", {"stream_t_s": pub.t_s, "valid": bool(pub.valid), "f0_hz": _num(pub.f0_hz),
                            "damping_ratio": _num(pub.zeta), "shaft_stiffness_nm_per_rad": _num(pub.c_s),
                            "shaft_damping_nm_s_per_rad": _num(pub.d_s)}
    if isinstance(pub, QualityOut):
        fpe = float(pub.fpe)
        return "quality", {"stream_t_s": pub.t_s, "residual_rms_rad_s": _num(pub.residual_rms),
                           "fpe_rms_rad_s": _num(math.sqrt(fpe)) if fpe >= 0 else None,
                           "excitation_rms_nm": _num(pub.excitation), "samples_used": int(pub.samples_used)}
    if isinstance(pub, StatusOut):
        return "status", {"stream_t_s": pub.t_s, "online": True, "state": pub.state.name,
                          "state_code": int(pub.state), "bad_frames": int(pub.bad_frames),
                          "missing_frames": int(pub.missing_frames)}
    return "alert", {"stream_t_s": pub.t_s, "kind": pub.kind.name, "kind_code": int(pub.kind),
                     "severity": SEVERITY.get(pub.severity, str(pub.severity)), "severity_code": int(pub.severity),
                     "change_pct": _num(pub.value_pct), "speed_rpm": _num(pub.speed_rpm), "message": pub.message}


def _tls(client, s: MqttSettings) -> None:
    try:
        client.tls_set(ca_certs=s.ca_file, certfile=s.cert_file, keyfile=s.key_file)
    except (OSError, ssl.SSLError) as err:
        key = "ca_file" if s.cert_file is None else "cert_file/key_file"
        raise ConfigError(f"mqtt.{key}: cannot load TLS files: {getattr(err, 'strerror', None) or err}") from None


def make_client(s: MqttSettings, client_id: str, password: str | None):
    """A paho client (MQTT 3.1.1, callback API 2) with credentials and TLS from the settings."""
    mqtt = _client_module()
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id, protocol=mqtt.MQTTv311)
    if s.username is not None:
        client.username_pw_set(s.username, password)
    if s.tls:
        _tls(client, s)
    client.reconnect_delay_set(min(0.5, s.reconnect_max_s), s.reconnect_max_s)
    return client


def broker_address(s: MqttSettings) -> tuple[str, int]:
    return str(s.host), s.port or (8883 if s.tls else 1883)


def refusal(reason, s: MqttSettings) -> str:
    """One line saying why the broker refused a connection."""
    host, port = broker_address(s)
    text = f"mqtt: broker {host}:{port} refused the connection: {reason}"
    if getattr(reason, "value", None) in AUTH_CODES:
        source = next((f"mqtt.{k}" for k in ("password_file", "password_env", "password") if getattr(s, k)),
                      "no password")
        text += f" (check mqtt.username {s.username!r} and {source})"
    return text


class MqttTelemetry:
    """Publications -> MQTT, buffered and never blocking the caller (see module notes).

    Attributes (read-only, for logs and tests): ``enqueued``, ``published``
    (acknowledged by the broker, or written for QoS 0), ``dropped`` (oldest
    messages dropped on a full buffer), ``connected``, ``fault`` (the last
    connection problem, ``None`` once connected).
    """

    def __init__(self, settings: MqttSettings, log: Callable[[str], None] = print, client=None) -> None:
        s = settings
        self.settings = s
        self.bench = bench_name(s)
        self.log = log
        self.root = f"{s.topic_prefix}/{self.bench}"
        self.capacity = s.buffer_messages
        self._buffer: deque = deque()
        self.enqueued = self.published = self.dropped = 0
        self.alerts_total = 0
        self._last_alert: dict | None = None
        self._last_retained: dict[str, str] = {}  # topic -> last payload handed to paho (sent again on reconnect)
        self._unacked = 0
        self._lock = threading.Lock()
        self.connected = False
        self.fault: str | None = None
        self._republish = False
        self._stop = threading.Event()
        self.address = broker_address(s)
        self.client = client or make_client(s, s.client_id or f"online-id-{self.bench}", resolve_password(s))
        self.client.will_set(f"{self.root}/status", json.dumps(
            {"bench": self.bench, "online": False, "state": "OFFLINE", "reason": "connection lost"}), 1, True)
        self.client.on_connect = self._on_connect
        self.client.on_connect_fail = self._on_connect_fail
        self.client.on_disconnect = self._on_disconnect
        self.client.on_publish = self._on_publish
        host, port = self.address
        self.client.connect_async(host, port, keepalive=max(5, round(s.keepalive_s)))
        self.client.loop_start()
        self._sender = threading.Thread(target=self._send_loop, name="online-id-mqtt", daemon=True)
        self._sender.start()

    # -- the receive loop's side: append only ------------------------------------------------------
    def publish(self, pubs: Iterable) -> None:
        """Queue publications (ExcitationOut is not telemetry); never waits (see module notes)."""
        buf, now = self._buffer, time.time()
        for pub in pubs:
            if type(pub) not in _PUBLISHED:
                continue
            if len(buf) >= self.capacity:
                try:
                    buf.popleft()
                    self.dropped += 1
                except IndexError:  # the sender took it meanwhile
                    pass
            self.enqueued += 1
            buf.append((self.enqueued, now, pub))

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    # -- paho's network thread -----------------------------------------------------------------------
    def _report(self, text: str | None) -> None:
        if text != self.fault:
            self.fault = text
            if text is not None:
                self.log(text)

    def _on_connect(self, client, userdata, flags, reason, properties) -> None:
        if reason.is_failure:
            self._report(refusal(reason, self.settings))
            return
        host, port = self.address
        self.log(f"mqtt: connected to {host}:{port} as bench {self.bench!r} "
                 f"({len(self._buffer)} messages waiting)")
        self.fault = None
        self._republish = True
        self.connected = True

    def _on_connect_fail(self, client, userdata) -> None:
        host, port = self.address
        err = sys.exc_info()[1]  # paho calls this inside its ``except OSError`` around the connection attempt
        if isinstance(err, ssl.SSLCertVerificationError):
            self._report(f"mqtt: broker {host}:{port}: TLS certificate not trusted ({err.verify_message}; check "
                         f"mqtt.ca_file {self.settings.ca_file!r}); buffering up to {self.capacity} messages, "
                         f"retrying")
        elif isinstance(err, ssl.SSLError):
            self._report(f"mqtt: broker {host}:{port}: TLS handshake failed ({err.reason or err}; check mqtt.tls, "
                         f"mqtt.port and the broker's listener); buffering up to {self.capacity} messages, retrying")
        else:
            self._report(f"mqtt: cannot reach broker {host}:{port}; buffering up to {self.capacity} messages, "
                         f"retrying")

    def _on_disconnect(self, client, userdata, flags, reason, properties) -> None:
        was, self.connected = self.connected, False
        if was and not self._stop.is_set():
            host, port = self.address
            self._report(f"mqtt: lost broker {host}:{port} ({reason}); buffering up to {self.capacity} "
                         f"messages, retrying")

    def _on_publish(self, client, userdata, mid, reason, properties) -> None:
        with self._lock:
            self._unacked -= 1
            self.published += 1

    # -- the sender thread ---------------------------------------------------------------------------
    def _hand(self, topic: str, body: str, qos: int, retain: bool) -> None:
        with self._lock:
            self._unacked += 1
        self.client.publish(topic, body, qos, retain)  # paho keeps it (and sends it again) until acknowledged

    def _encode(self, seq: int, t_unix: float, pub) -> tuple[str, str, int, bool]:
        kind, fields = payload(pub)
        head = {"bench": self.bench, "seq": seq, "time_unix_s": round(t_unix, 3)}
        if kind == "alert":
            if pub.kind:
                self.alerts_total += 1
            self._last_alert = {"kind": fields["kind"], "severity": fields["severity"],
                                "message": fields["message"], "time_unix_s": head["time_unix_s"]}
        elif kind == "status":
            fields |= {"alerts_total": self.alerts_total, "last_alert": self._last_alert,
                       "telemetry_dropped_messages": self.dropped}
        topic = f"{self.root}/{kind}"
        body = json.dumps(head | fields, allow_nan=False)
        if kind == "alert":
            return topic, body, max(1, self.settings.qos), False
        self._last_retained[topic] = body
        return topic, body, self.settings.qos, True

    def _drain(self) -> None:
        if self._republish:  # a restarted broker may have lost the retained messages: send the last ones again
            self._republish = False
            for topic, body in list(self._last_retained.items()):
                self._hand(topic, body, self.settings.qos, True)
        while self.connected and self._buffer and self._unacked < IN_FLIGHT:
            try:
                item = self._buffer.popleft()
            except IndexError:
                break
            self._hand(*self._encode(*item))

    def _send_loop(self) -> None:
        while not self._stop.wait(POLL_S):
            if self.connected:
                self._drain()

    def idle(self) -> bool:
        """True when everything queued has been acknowledged."""
        return not self._buffer and self._unacked <= 0

    def close(self, state: str, timeout_s: float = 2.0) -> None:
        """Send what is buffered (for at most ``timeout_s`` while connected), mark the bench stopped, disconnect."""
        deadline = time.monotonic() + timeout_s
        while self.connected and not self.idle() and time.monotonic() < deadline:
            time.sleep(POLL_S)
        self._stop.set()
        self._sender.join(1.0)
        if self.connected:
            info = self.client.publish(f"{self.root}/status", json.dumps(
                {"bench": self.bench, "online": False, "state": "STOPPED", "last_state": state,
                 "time_unix_s": round(time.time(), 3), "reason": "service stopped"}), 1, True)
            try:
                info.wait_for_publish(max(0.1, deadline - time.monotonic()))
            except (RuntimeError, ValueError):
                pass
        self.client.disconnect()
        self.client.loop_stop()
        unsent = len(self._buffer) + max(0, self._unacked)
        self.log(f"mqtt: {self.published} messages published, {self.dropped} dropped (buffer full), "
                 f"{unsent} unsent at stop")


_PUBLISHED = {EstimateOut, QualityOut, StatusOut, AlertOut}


class FleetSubscriber:
    """A subscriber to every bench's telemetry (``<prefix>/+/+``); ``on_message(topic, payload)`` per message.

    Messages are handled on paho's network thread.  ``fault`` holds the last
    connection problem as one line.
    """

    def __init__(self, settings: MqttSettings, on_message: Callable[[str, bytes], None]) -> None:
        s = settings
        self.settings = s
        self.fault: str | None = None
        self._subscribed = threading.Event()
        self.client = make_client(s, f"online-id-fleet-{socket.gethostname()}-{os.getpid()}", resolve_password(s))
        self.client.on_connect = self._on_connect
        self.client.on_connect_fail = self._on_connect_fail
        self.client.on_subscribe = lambda *_: self._subscribed.set()
        self.client.on_message = lambda client, userdata, m: on_message(m.topic, m.payload)
        host, port = broker_address(s)
        self.client.connect_async(host, port, keepalive=max(5, round(s.keepalive_s)))
        self.client.loop_start()

    def _on_connect(self, client, userdata, flags, reason, properties) -> None:
        if reason.is_failure:
            self.fault = refusal(reason, self.settings)
        else:
            self.fault = None
            client.subscribe(f"{self.settings.topic_prefix}/+/+", qos=1)

    def _on_connect_fail(self, client, userdata) -> None:
        host, port = broker_address(self.settings)
        self.fault = f"mqtt: cannot reach broker {host}:{port}"

    def wait_subscribed(self, timeout_s: float) -> None:
        """Return once subscribed; OnlineIdError with the reason if the broker cannot be used."""
        deadline = time.monotonic() + timeout_s
        while not self._subscribed.wait(0.05):
            if self.fault:
                raise OnlineIdError(self.fault)
            if time.monotonic() > deadline:
                host, port = broker_address(self.settings)
                raise OnlineIdError(f"mqtt: no answer from broker {host}:{port} within {timeout_s:g} s")

    def __enter__(self) -> "FleetSubscriber":
        return self

    def __exit__(self, *exc) -> None:
        self.client.disconnect()
        self.client.loop_stop()
