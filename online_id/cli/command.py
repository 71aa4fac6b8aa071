"""``online-id ack`` and ``online-id relearn``: send a command frame to the running service.

The service listens for the ``OidCommand`` frame on its bus (a bench PC or
operator panel can send the same frame); these commands open the bus of the
configuration, send the frame and exit.  ``relearn`` sends it twice, 0.2 s
apart with consecutive counters: the service's default policy
(``commands.relearn: confirm``) acts only on a confirmed RELEARN.  The
counter follows the clock (20 per second), so that commands sent one after
another never repeat a counter the service has just accepted.

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

from online_id.cli import command_help
from online_id.cli.bus_options import add_bus_options, with_bus_options
from online_id.config import load_config
from online_id.errors import ConfigError, DbcError
from online_id.io.bus import CanBus
from online_id.io.dbc import BenchCommand, encode_command, load_dbc

COMMANDS = {"ack": BenchCommand.ACK_ALERT, "relearn": BenchCommand.RELEARN_BASELINE}


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    for name in COMMANDS:
        text = command_help(name)
        p = subparsers.add_parser(name, help=text, description=f"Send the service a command frame: {text}.")
        p.add_argument("--config", metavar="FILE", help="the service's YAML configuration (bus, DBC, mapping)")
        add_bus_options(p)
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


_last_counter: int | None = None  # the last alive counter this process sent (see run)


def run(args: argparse.Namespace) -> int:
    s = with_bus_options(load_config(args.config), args)
    if getattr(args, "from_log", None):
        return relearn_from(args.from_log, args.state, s)
    if getattr(args, "state", None) is not None:
        raise ConfigError("relearn: --state needs --from LOG (a running service keeps its own state)")
    command = COMMANDS[args.command_name]
    db = load_dbc(s.dbc)
    global _last_counter
    repeats = 2 if command == BenchCommand.RELEARN_BASELINE else 1
    # the clock's counter, but never one this process has used: two commands within one 50 ms tick (a
    # script, or `ack` then `relearn` in one process) would repeat it, and the service refuses a repeat
    counter = int(time.time() * 20)
    if _last_counter is not None:
        counter = max(counter, _last_counter + 1)
    _last_counter = counter + repeats - 1
    frames = [encode_command(db, s.mapping.command_message, s.mapping.command_signal, command, counter + k,
                             crc=s.mapping.command_crc) for k in range(repeats)]
    interface, channel = s.bus.interface, s.bus.channel
    with CanBus(interface, channel, s.bus.bitrate) as bus:
        for k, (ident, data) in enumerate(frames):
            if k:
                time.sleep(0.2)
            bus.send(ident, data)
        sent = ", ".join(data.hex().upper() for _, data in frames)
        print(f"sent {command.name} (ID 0x{frames[0][0]:X} data {sent}) on {interface}:{channel}")
        if not args.wait > 0:
            return 0
        answer = await_answer(bus, s, (counter + repeats - 1) % 256, args.wait)
    if answer is None:
        print(f"no answer from the service within {args.wait:g} s on {interface}:{channel} (is it running there? "
              f"it answers on its status frame, signal CommandCounterEcho)")
        return 1
    print(f"service answered: {answer['LastCommand']} {answer['CommandResult']} (state {answer['State']})"
          + ("; its log says why" if answer["CommandResult"] != "ACCEPTED" else ""))
    return 0 if answer["CommandResult"] == "ACCEPTED" else 1


def await_answer(bus: CanBus, s, counter: int, wait_s: float) -> dict | None:
    """The service's status frame answering the command frame of alive counter ``counter``, or None."""
    from online_id.io.dbc_output import OutputEncoder

    codec = OutputEncoder(load_dbc(s.dbc), source=s.dbc or "online_id.dbc")
    status_id = next(fid for fid, name in codec.output_ids(s.publish.frame_ids).items() if name == "OidStatus")
    end = time.monotonic() + wait_s
    while time.monotonic() < end:
        frame = bus.recv(0.05)
        if frame is None or frame.arbitration_id != status_id:
            continue
        try:
            values, _ = codec.decode_named("OidStatus", frame.data)
        except DbcError:
            continue
        if values.get("CommandCounterEcho") == counter % 64 and values.get("CommandResult") != "NONE":
            return values
    return None


def relearn_from(log: str, directory: Path | None, settings) -> int:
    """Learn the baselines from a reference log into the state of ``directory`` (see module notes)."""
    from online_id.cli.replay import keep, replay, restore, state_file
    from online_id.progress import Progress
    from online_id.runtime import Runtime
    from online_id.service import state_path

    path = state_file(directory) if directory is not None else state_path(settings)
    if path is None:
        raise ConfigError("relearn --from: no state directory: give --state DIR or state.directory in the config")
    runtime = Runtime(settings)
    restored = restore(runtime, path)
    pipe = runtime.pipeline
    pipe.baseline.reset()
    pipe._references.clear()
    pipe.detector.reset()
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
