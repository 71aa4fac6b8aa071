"""``online-id monitor``: the service's output frames and health, live, decoded with the DBC.

Like ``cantools monitor`` or ``can.viewer`` for the frames the service
publishes (OidEstimate, OidShaft, OidQuality, OidStatus, OidAlert,
OidExcitation; the config's DBC and ``publish.frame_ids``), on any
python-can interface.  Every frame is checked as a consumer would check it
(CRC-8 in byte 7, the 4-bit alive counter without jumps, every value within
its DBC range and, for an enumeration, one of its defined values), and the
view says when the service has gone silent.  An 8-bit CRC passes one random
frame in 256: a frame that passes it with a value the DBC does not allow
(``State 238``) is marked suspect, counted, and its values are not shown.

On a terminal the view is redrawn in place twice a second; otherwise (a
pipe, a log file) or with ``--json`` it prints one line per received frame,
so that it can be recorded or read by another program.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from online_id.config import load_config
from online_id.errors import ConfigError, DbcError

if TYPE_CHECKING:
    from online_id.io.dbc_output import OutputEncoder
from online_id.cli import command_help
from online_id.cli.bus_options import add_bus_options, with_bus_options

SILENT_S = 2.0
"""No status frame for this long: the service is reported silent."""


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "monitor", help=command_help("monitor"),
        description="Listen on the service's bus and show its output frames (estimate, shaft, quality, status, "
                    "alerts, excitation) decoded with the config's DBC, with CRC and alive-counter checks and "
                    "the time since each was last seen. On a terminal the view refreshes in place; otherwise, or "
                    "with --json, one line per frame.")
    p.add_argument("--config", metavar="FILE", help="the service's YAML configuration (bus, DBC, publish)")
    add_bus_options(p)
    p.add_argument("--json", action="store_true", help="one JSON document per frame (never the live view)")
    p.add_argument("--max-seconds", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    p.set_defaults(func=run)


@dataclass
class Seen:
    """What was received of one output message."""

    count: int = 0
    t_s: float = 0.0  # when the last frame came (s since the start)
    values: dict = field(default_factory=dict)
    counter: int | None = None
    counter_jumps: int = 0
    suspect: int = 0  # frames with a valid CRC but values the DBC does not allow


def _limits(message: Any) -> dict[str, tuple[float, float, dict[int, str] | None]]:
    """Signal -> (lowest, highest physical value allowed, defined values or None), from the DBC."""
    from online_id.io.dbc import signal_bounds

    return {sig.name: (*signal_bounds(sig), {int(k): str(v) for k, v in sig.choices.items()} if sig.choices else None)
            for sig in message.signals}


def suspect_values(values: dict, limits: dict[str, tuple[float, float, dict[int, str] | None]]) -> list[str]:
    """What in a decoded frame the DBC does not allow: a value outside its range, an undefined enumeration."""
    bad = []
    for name, value in values.items():
        if isinstance(value, str) or name not in limits:  # an enumeration's name: a defined value
            continue
        lo, hi, choices = limits[name]
        if choices is not None:
            bad.append(f"{name} {value:g} is not a defined value ({', '.join(f'{k} {v}' for k, v in choices.items())})")
        elif not lo <= value <= hi:
            bad.append(f"{name} {value:g} is outside its DBC range [{lo:g}, {hi:g}]")
    return bad


class Watch:
    """Decode and check the service's output frames (no I/O: :meth:`take` gets frames, returns records)."""

    def __init__(self, codec: OutputEncoder, ids: dict[int, str], db: Any,
                 units: dict[str, dict[str, str]] | None = None) -> None:
        self.codec = codec
        self.ids = ids
        self.units = units or {}  # message -> signal -> unit, from the DBC
        self.seen: dict[str, Seen] = {name: Seen() for name in ids.values()}
        self.limits = {name: _limits(db.get_message_by_name(name)) for name in ids.values()}
        self.alerts: list[dict] = []
        self.crc_errors = 0
        self.suspect = 0
        self.frames = 0

    def take(self, t_s: float, arbitration_id: int, data: bytes) -> dict | None:
        """One frame from the bus: its record (``message``, ``signals``; or ``error``), None if not an output."""
        name = self.ids.get(arbitration_id)
        if name is None:
            return None
        self.frames += 1
        record: dict = {"t_s": round(t_s, 6), "id": f"0x{arbitration_id:X}", "message": name}
        try:
            values, counter = self.codec.decode_named(name, data)
        except DbcError:
            self.crc_errors += 1
            record["error"] = f"bad CRC or length: data {bytes(data).hex().upper()}"
            return record
        s = self.seen[name]
        bad = suspect_values(values, self.limits[name])
        if bad:  # a frame that passed the CRC by chance, or a sender that is not the service: values not shown
            self.suspect += 1
            s.suspect += 1
            record["suspect"] = f"{'; '.join(bad)}: data {bytes(data).hex().upper()}, values not shown"
            return record
        if s.counter is not None and counter != (s.counter + 1) % 16:
            s.counter_jumps += 1
            record["counter_jump"] = [s.counter, counter]
        s.count, s.t_s, s.values, s.counter = s.count + 1, t_s, values, counter
        if name == "OidAlert":
            self.alerts = (self.alerts + [dict(values, t_s=t_s)])[-5:]
        record["signals"] = values
        record["units"] = {k: u for k, u in self.units.get(name, {}).items() if u and k in values}
        return record


def _fmt(values: dict, units: dict | None = None) -> str:
    """``Signal value unit`` pairs (the unit from the DBC, where it has one)."""
    units = units or {}
    return "  ".join((f"{k} {v:.6g}" if isinstance(v, float) else f"{k} {v}") + (f" {units[k]}" if units.get(k) else "")
                     for k, v in values.items())


def line(record: dict) -> str:
    """One text line for a frame's record."""
    head = f"{record['t_s']:.3f} {record['id']} {record['message']}"
    if "error" in record:
        return f"{head}: {record['error']}"
    if "suspect" in record:
        return f"{head}: SUSPECT: {record['suspect']}"
    jump = f"  (alive counter jumped {record['counter_jump'][0]} -> {record['counter_jump'][1]})" \
        if "counter_jump" in record else ""
    return f"{head}  {_fmt(record['signals'], record.get('units'))}{jump}"


def screen(watch: Watch, now: float, where: str) -> str:
    """The live view at ``now`` s since the start: one row per output message, alerts, health."""
    status = watch.seen.get("OidStatus")
    silent = status is None or status.count == 0 or now - status.t_s > SILENT_S
    health = ("SILENT: no status frame for " + (f"{now - status.t_s:.1f} s" if status and status.count else
                                                 "the whole time") if silent else "alive")
    rows = [f"online-id monitor  {where}  {now:6.1f} s  {watch.frames} frames  service {health}",
            f"checks: {watch.crc_errors} CRC errors, "
            f"{sum(s.counter_jumps for s in watch.seen.values())} alive-counter jumps, "
            f"{watch.suspect} suspect frames (values outside the DBC)", ""]
    for name, s in watch.seen.items():
        age = f"{now - s.t_s:5.1f} s ago" if s.count else "never seen"
        rows.append(f"{name:<14} {s.count:7d} frames  {age}  {_fmt(s.values, watch.units.get(name))}"
                    + (f"  ({s.suspect} suspect)" if s.suspect else ""))
    rows += ["", f"last alerts ({len(watch.alerts)}):"]
    rows += [f"  {a['t_s']:7.1f} s  {_fmt({k: v for k, v in a.items() if k != 't_s'}, watch.units.get('OidAlert'))}"
             for a in watch.alerts]
    return "\n".join(rows)


def open_watch(args: argparse.Namespace):
    """The config, a :class:`Watch` of its outputs, and the bus description."""
    from online_id.io.dbc import load_dbc
    from online_id.io.dbc_output import OutputEncoder

    s = with_bus_options(load_config(args.config), args)
    db = load_dbc(s.dbc)
    codec = OutputEncoder(db, source=s.dbc or "online_id.dbc")
    ids = codec.output_ids(s.publish.frame_ids)
    units = {name: {sig.name: sig.unit or "" for sig in db.get_message_by_name(name).signals} for name in ids.values()}
    return s, Watch(codec, ids, db, units), s.bus.interface, s.bus.channel


def run(args: argparse.Namespace) -> int:
    from online_id.io.bus import CanBus

    if args.max_seconds is not None and not args.max_seconds > 0:
        raise ConfigError(f"--max-seconds: expected a number > 0, but got {args.max_seconds!r}")
    s, watch, interface, channel = open_watch(args)
    live = sys.stdout.isatty() and not args.json
    t0 = time.monotonic()
    end = None if args.max_seconds is None else time.monotonic() + args.max_seconds
    drawn = -1.0
    with CanBus(interface, channel, s.bus.bitrate, options=s.bus.options) as bus:
        while end is None or time.monotonic() < end:
            frame = bus.recv(0.1)
            now = time.monotonic() - t0  # seconds since the start (the frames' times are the bus's own)
            if frame is not None and not frame.is_error:
                record = watch.take(now, frame.arbitration_id, frame.data)
                if record is not None and not live:
                    print(json.dumps(record) if args.json else line(record), flush=True)
            if live and now - drawn >= 0.5:
                drawn = now
                sys.stdout.write("\x1b[H\x1b[J" + screen(watch, now, f"{interface}:{channel}") + "\n")
                sys.stdout.flush()
    if watch.frames == 0:
        print(f"no output frame of the service in {time.monotonic() - t0:.1f} s on {interface}:{channel} "
              f"(is it running there? IDs {', '.join(f'0x{i:X}' for i in sorted(watch.ids))})", file=sys.stderr)
        return 1
    return 0
