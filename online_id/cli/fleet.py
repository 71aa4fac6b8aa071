"""``online-id fleet --broker HOST[:PORT]``: one table of every bench publishing to an MQTT broker.

A subscriber to ``<prefix>/+/estimate|quality|status|alert`` (see
:mod:`online_id.io.mqtt` for the topic tree and payloads): the retained
messages give each bench's latest estimate, quality and status at once,
alerts come as they are raised (and the status carries the last one).
``--once`` prints the table after ``--wait`` seconds; otherwise it is
redrawn every ``--interval`` seconds until Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import threading
import time

from online_id.errors import ConfigError, printable
from online_id.cli import command_help


class Fleet:
    """The latest payload of each kind per bench, from the messages seen."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix.rstrip("/")
        self.benches: dict[str, dict[str, dict]] = {}
        self.alerts_seen: dict[str, int] = {}
        self.ignored = 0
        self.lock = threading.Lock()

    def update(self, topic: str, body: bytes) -> None:
        rest = topic[len(self.prefix) + 1:] if topic.startswith(self.prefix + "/") else ""
        bench, _, kind = rest.partition("/")
        try:
            data = json.loads(body)
        except (ValueError, UnicodeDecodeError):
            data = None
        if not bench or kind not in ("estimate", "quality", "status", "alert") or not isinstance(data, dict):
            self.ignored += 1
            return
        with self.lock:
            entry = self.benches.setdefault(bench, {})
            entry[kind] = data
            if kind == "alert" and data.get("kind") != "NONE":
                self.alerts_seen[bench] = self.alerts_seen.get(bench, 0) + 1

    def table(self, now_unix_s: float, width: int | None = None) -> str:
        """One line per bench (see the header for the columns and their units).

        Every column is as wide as its widest cell; the last (LAST ALERT) is
        cut only to fit ``width`` characters (a terminal's), never otherwise.
        """
        head = ["BENCH", "STATE", "f0 [Hz]", "zeta [-]", "c_s [Nm/rad]", "resid [rad/s]", "exc [Nm]", "age [s]",
                "ALERTS", "LAST ALERT"]
        left = {0, 1, 9}  # text columns; the numbers align right
        rows = []
        with self.lock:
            items = sorted(self.benches.items())
        for bench, entry in items:
            est, q, st = entry.get("estimate", {}), entry.get("quality", {}), entry.get("status", {})
            valid = bool(est.get("valid"))
            last = entry.get("alert") or st.get("last_alert")
            if last and last.get("kind") == "NONE":
                last = None
            stamps = [p.get("time_unix_s") for p in (est, q, st) if isinstance(p.get("time_unix_s"), (int, float))]
            alerts = max(int(st.get("alerts_total") or 0), self.alerts_seen.get(bench, 0))
            last_text = (f"{last.get('kind')} {last.get('severity')}: {last.get('message', '')}" if last else "")
            rows.append([printable(bench), printable(str(st.get("state", "?"))),
                         _cell(est.get("f0_hz") if valid else None, ".2f"),
                         _cell(est.get("damping_ratio") if valid else None, ".3f"),
                         _cell(est.get("shaft_stiffness_nm_per_rad") if valid else None, ".0f"),
                         _cell(q.get("residual_rms_rad_s"), ".4f"), _cell(q.get("excitation_rms_nm"), ".1f"),
                         f"{now_unix_s - max(stamps):.1f}" if stamps else "-", str(alerts), printable(last_text)])
        widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
        lines = []
        for r in [head] + rows:
            cells = [c.ljust(w) if i in left else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))]
            line = " ".join(cells[:-1]) + "  " + r[-1]
            lines.append(line[:width] if width else line)
        if not rows:
            lines.append(f"(no bench has published under {self.prefix}/ yet)")
        return "\n".join(lines)


def _cell(value, fmt: str) -> str:
    return format(value, fmt) if isinstance(value, (int, float)) and not isinstance(value, bool) else "-"


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "fleet",
        help=command_help("fleet"),
        description="Subscribe to the benches' MQTT telemetry and show one table: state, latest estimate, "
        "quality and alerts per bench. Credentials and TLS as in the service's mqtt section.",
    )
    p.add_argument("--broker", metavar="HOST[:PORT]", help="the MQTT broker (default: mqtt.host of --config)")
    p.add_argument("--config", metavar="FILE", help="take broker, credentials, TLS and topic prefix from the "
                   "mqtt section of this service config")
    p.add_argument("--username")
    p.add_argument("--password-file", metavar="FILE")
    p.add_argument("--password-env", metavar="VAR", help="environment variable holding the password")
    p.add_argument("--tls", action="store_true", help="connect with TLS (default port 8883)")
    p.add_argument("--ca-file", metavar="FILE", help="CA certificates for TLS (default: the system's)")
    p.add_argument("--topic-prefix", metavar="PREFIX", help="default online-id")
    p.add_argument("--once", action="store_true", help="print the table once and exit")
    p.add_argument("--wait", type=float, default=1.0, metavar="S",
                   help="with --once: listen this long after subscribing (default 1 s)")
    p.add_argument("--interval", type=float, default=1.0, metavar="S", help="redraw every S seconds (default 1)")
    p.set_defaults(func=run)


def _settings(args: argparse.Namespace):
    import dataclasses

    from online_id.config import MqttSettings, load_config

    base = load_config(args.config).mqtt if args.config else MqttSettings()
    over: dict = {}
    if args.broker:
        host, sep, port = args.broker.rpartition(":") if ":" in args.broker else (args.broker, "", "")
        if sep and not port.isdigit():
            raise ConfigError(f"--broker: expected HOST or HOST:PORT, got {args.broker!r}")
        over |= {"host": host, "port": int(port) if sep else None}
    for key in ("username", "password_file", "password_env", "ca_file", "topic_prefix"):
        if getattr(args, key) is not None:
            over[key] = getattr(args, key)
    if args.password_file or args.password_env:
        over |= {k: None for k in ("password", "password_file", "password_env") if k not in over}
    if args.tls or args.ca_file:
        over["tls"] = True
    try:
        s = dataclasses.replace(base, **over)
    except ConfigError as err:
        raise ConfigError(f"fleet: {getattr(err, 'key', '')}: {getattr(err, 'reason', err)}") from None
    if not s.host:
        raise ConfigError("fleet: give --broker HOST[:PORT] (or --config with mqtt.host)")
    return s


def run(args: argparse.Namespace) -> int:
    from online_id.io.mqtt import FleetSubscriber

    s = _settings(args)
    fleet = Fleet(s.topic_prefix)
    with FleetSubscriber(s, fleet.update) as sub:
        sub.wait_subscribed(timeout_s=max(args.wait, 1.0) + 4.0)
        if args.once:
            time.sleep(max(0.0, args.wait))
            print(fleet.table(time.time()))
            return 0
        tty = sys.stdout.isatty()
        try:
            while True:
                if tty:
                    print("\x1b[H\x1b[2J", end="")
                print(fleet.table(time.time(), shutil.get_terminal_size().columns if tty else None))
                if sub.fault:  # the view stays, with what is wrong under it; paho keeps reconnecting
                    print(printable(sub.fault))
                print("" if not tty else f"(every {args.interval:g} s; Ctrl-C ends)", flush=True)
                time.sleep(max(0.1, args.interval))
        except KeyboardInterrupt:
            return 0
