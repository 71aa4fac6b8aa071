"""``online-id ack`` and ``online-id relearn``: send a command frame to the running service.

The service listens for the ``OidCommand`` frame on its bus (a bench PC or
operator panel can send the same frame, see the DBC and docs/security.md);
these commands open the bus of the configuration, ask the service for its
command freshness value (a ``NONE`` command frame, answered at once with
``OidFreshness``), send the command with the next freshness value and, with
``--key-file`` (or ``commands.key_file`` of the config), its MAC, and exit.
``relearn`` sends it twice, 0.2 s apart with consecutive freshness values:
the service's default policy (``commands.relearn: confirm``) acts only on a
confirmed RELEARN.

Both then wait (``--wait``, 2 s) for the service's answer: the status
frame it sends at once after a command frame, whose ``CommandResult`` says
what it did (accepted, awaiting confirmation, refused) and whose
``CommandCounterEcho`` names the frame; they exit 1 when it was not
accepted or no answer came.

``online-id relearn --from LOG [--state DIR]`` sends nothing: it learns the
baselines from a healthy reference log (an acceptance run after a shaft
change, a run of an earlier day) through the service pipeline and writes
them into the service's state (the latched alarms and the detector's
statistics start afresh); the cells are marked as learned from that
reference run, and alerts name it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from online_id.cli import command_help
from online_id.cli.bus_options import add_bus_options, with_bus_options
from online_id.config import load_config
from online_id.errors import ConfigError, DbcError
from online_id.io.auth import read_key

if TYPE_CHECKING:
    from online_id.io.bus import CanBus

COMMANDS = {"ack": "ACK_ALERT", "relearn": "RELEARN_BASELINE"}
"""Subcommand -> the name of its :class:`~online_id.io.dbc.BenchCommand`."""
FRESHNESS_WAIT_S = 2.0
"""How long to wait for the service's freshness value with ``--wait 0``."""


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    for name in COMMANDS:
        text = command_help(name)
        p = subparsers.add_parser(name, help=text, description=f"Send the service a command frame: {text}.")
        p.add_argument("--config", metavar="FILE", help="the service's YAML configuration (bus, DBC, mapping)")
        add_bus_options(p)
        p.add_argument("--key-file", metavar="FILE",
                       help="the key (hex) of authenticated commands (default: commands.key_file of the config)")
        p.add_argument("--wait", type=float, default=2.0, metavar="S",
                       help="wait up to S seconds for the service's answer on its status frame (default 2; 0: "
                            "send only)")
        if name == "relearn":
            p.add_argument("--from", dest="from_log", metavar="LOG",
                           help="send nothing: learn the baselines from this healthy reference log (.log, .asc, "
                           ".blf) and write them into the state in --state DIR (default: state.directory)")
            p.add_argument("--state", metavar="DIR", type=Path,
                           help="with --from: the service's state directory")
        p.set_defaults(func=run, command_name=name)


def run(args: argparse.Namespace) -> int:
    from online_id.io.bus import CanBus
    from online_id.io.dbc import BenchCommand, encode_command, load_dbc

    s = with_bus_options(load_config(args.config), args)
    if getattr(args, "from_log", None):
        return relearn_from(args.from_log, args.state, s)
    if getattr(args, "state", None) is not None:
        raise ConfigError("relearn: --state needs --from LOG (a running service keeps its own state)")
    command = BenchCommand[COMMANDS[args.command_name]]
    db = load_dbc(s.dbc)
    key_file = args.key_file or s.commands.key_file
    key = read_key(key_file, "--key-file" if args.key_file else "commands.key_file") if key_file else None
    m = s.mapping
    repeats = 2 if command == BenchCommand.RELEARN_BASELINE else 1
    interface, channel = s.bus.interface, s.bus.channel
    with CanBus(interface, channel, s.bus.bitrate, options=s.bus.options) as bus:
        wait_s = args.wait if args.wait > 0 else FRESHNESS_WAIT_S
        fresh = ask_freshness(bus, s, db, wait_s)
        if fresh is None:
            print(f"no answer from the service within {wait_s:g} s on {interface}:{channel} (is it running "
                  f"there? it answers a NONE command frame with its freshness value, message OidFreshness)")
            return 1
        last, authenticated = fresh
        if authenticated and key is None:
            raise ConfigError("the service expects authenticated commands: give --key-file FILE (or "
                              "commands.key_file in the config) with its key")
        frames = [encode_command(db, m.command_message, m.command_signal, command, last + 1 + k, m.command_crc,
                                 key=key, freshness_signal=m.command_freshness, mac_signal=m.command_mac)
                  for k in range(repeats)]
        for k, (ident, data) in enumerate(frames):
            if k:
                time.sleep(0.2)
            bus.send(ident, data)
        sent = ", ".join(data.hex().upper() for _, data in frames)
        print(f"sent {command.name} (ID 0x{frames[0][0]:X} data {sent}, freshness {last + 1}"
              f"{'' if repeats == 1 else f'..{last + repeats}'}, {'with a MAC' if key else 'no MAC'}) on "
              f"{interface}:{channel}")
        if not args.wait > 0:
            return 0
        answer = await_answer(bus, s, last + repeats, args.wait)
    if answer is None:
        print(f"no answer from the service within {args.wait:g} s on {interface}:{channel} (is it running there? "
              f"it answers on its status frame, signal CommandCounterEcho)")
        return 1
    print(f"service answered: {answer['LastCommand']} {answer['CommandResult']} (state {answer['State']})"
          + ("; its log says why" if answer["CommandResult"] != "ACCEPTED" else ""))
    return 0 if answer["CommandResult"] == "ACCEPTED" else 1


def _codec(s, db=None):
    from online_id.io.dbc import load_dbc
    from online_id.io.dbc_output import OutputEncoder

    codec = OutputEncoder(db if db is not None else load_dbc(s.dbc), source=s.dbc or "online_id.dbc")
    return codec, {name: fid for fid, name in codec.output_ids(s.publish.frame_ids).items()}


def _await(bus: CanBus, codec, frame_id: int, name: str, wanted, wait_s: float) -> dict | None:
    """The values of the first frame of output ``name`` (ID ``frame_id``) within ``wait_s`` that ``wanted``
    accepts, or None."""
    end = time.monotonic() + wait_s
    while time.monotonic() < end:
        frame = bus.recv(0.05)
        if frame is None or frame.arbitration_id != frame_id:
            continue
        try:
            values, _ = codec.decode_named(name, frame.data)
        except DbcError:
            continue
        if wanted(values):
            return values
    return None


def ask_freshness(bus: CanBus, s, db, wait_s: float = FRESHNESS_WAIT_S) -> tuple[int, bool] | None:
    """Send a NONE command frame and read the service's answer: (last accepted freshness value, whether it
    expects a MAC), or None when no answer came within ``wait_s``."""
    from online_id.io.dbc import BenchCommand, encode_command

    codec, ids = _codec(s, db)
    if "OidFreshness" not in ids:
        raise ConfigError(f"{s.dbc or 'online_id.dbc'}: no OidFreshness message: the service cannot tell a "
                          f"sender its command freshness value (add it from the packaged online_id.dbc)")
    m = s.mapping
    bus.send(*encode_command(db, m.command_message, m.command_signal, BenchCommand.NONE, 0, m.command_crc,
                             freshness_signal=m.command_freshness, mac_signal=m.command_mac))
    values = _await(bus, codec, ids["OidFreshness"], "OidFreshness", lambda v: True, wait_s)
    return None if values is None else (int(values["FreshnessValue"]), values["Authenticated"] != "PLAIN")


def await_answer(bus: CanBus, s, freshness: int, wait_s: float) -> dict | None:
    """The service's status frame answering the command frame of freshness value ``freshness``, or None
    (the echo: the frame's freshness bits modulo 64)."""
    codec, ids = _codec(s)
    return _await(bus, codec, ids["OidStatus"], "OidStatus",
                  lambda v: v.get("CommandCounterEcho") == freshness % 64 and v.get("CommandResult") != "NONE",
                  wait_s)


def relearn_from(log: str, directory: Path | None, settings) -> int:
    """Learn the baselines from a reference log into the state of ``directory`` (see module notes)."""
    from online_id.offline.replay import keep, replay, restore, state_file
    from online_id.progress import Progress
    from online_id.service.runtime import Runtime
    from online_id.service.live import state_path

    path = state_file(directory) if directory is not None else state_path(settings)
    if path is None:
        raise ConfigError("relearn --from: no state directory: give --state DIR or state.directory in the config")
    runtime = Runtime(settings)
    restored = restore(runtime, path)
    pipe = runtime.pipeline
    pipe.policy.relearn()  # what the RELEARN command forgets, the engaged flank and reference windows too
    pipe.alerts.clear()
    pipe.run_label = f"reference run {Path(log).name}"
    pipe.reference_run = True
    with Progress("relearn", unit="frames") as progress:
        replay(log, runtime, progress=progress, require_match=True)
    drift = [a for a in pipe.alerts if a.kind.name in ("FREQ_DRIFT", "DAMPING_DRIFT")]
    pipe.detector.reset()  # the reference run's own statistics are no change
    pipe.alerts.clear()
    keep(runtime, path)
    learned = [b for b in pipe.baseline.bands if b.count >= pipe.baseline.min_count and b.kind != "held"]
    print(f"online-id relearn --from {log}: {len(learned)} cells learned "
          f"({len(pipe.baseline.bands) - len(learned)} still learning or held), "
          f"state {'updated' if restored else 'written'} in {path}")
    for b in learned:
        print(f"  {b.band[0]:.0f}-{b.band[1]:.0f} rpm, {b.load_nm:.1f} Nm: f0 {b.mean_f:.3f} +- {b.std_f:.3f} Hz, "
              f"zeta {b.mean_zeta:.4f} +- {b.std_zeta:.4f} ({b.count} estimates)")
    if drift:
        print(f"  warning: {len(drift)} drift alarms during the reference log; is it healthy? first: "
              f"{drift[0].message}")
    if not learned:
        print("  warning: no cell learned (too short, or not excited: a cell needs "
              f"{pipe.baseline.min_count} s of steady, well-excited estimates)")
    return 0
