"""``online-id ack`` and ``online-id relearn``: send a command frame to the running service.

The service listens for the ``OidCommand`` frame on its bus (a bench PC or
operator panel can send the same frame); these commands open the bus of the
configuration, send the frame and exit.  ``relearn`` sends it twice, 0.2 s
apart with consecutive counters: the service's default policy
(``commands.relearn: confirm``) acts only on a confirmed RELEARN.  The
counter follows the clock (20 per second), so that commands sent one after
another never repeat a counter the service has just accepted.
"""

from __future__ import annotations

import argparse
import time

from online_id.config import load_config
from online_id.io.bus import CanBus
from online_id.io.dbc import BenchCommand, encode_command, load_dbc

COMMANDS = {
    "ack": (BenchCommand.ACK_ALERT, "acknowledge the latched alerts (they clear and detection restarts)"),
    "relearn": (BenchCommand.RELEARN_BASELINE, "forget the learned baselines and learn them anew "
                                               "(after a planned shaft change)"),
}


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    for name, (_cmd, text) in COMMANDS.items():
        p = subparsers.add_parser(name, help=text, description=f"Send the service a command frame: {text}.")
        p.add_argument("--config", metavar="FILE", help="the service's YAML configuration (bus, DBC, mapping)")
        p.add_argument("--interface", help="override bus.interface")
        p.add_argument("--channel", help="override bus.channel")
        p.set_defaults(func=run, command_name=name)


def run(args: argparse.Namespace) -> int:
    s = load_config(args.config)
    command = COMMANDS[args.command_name][0]
    db = load_dbc(s.dbc)
    counter = int(time.time() * 20)
    repeats = 2 if command == BenchCommand.RELEARN_BASELINE else 1
    frames = [encode_command(db, s.mapping.command_message, s.mapping.command_signal, command, counter + k,
                             crc=s.mapping.command_crc) for k in range(repeats)]
    interface = args.interface or s.bus.interface
    channel = args.channel or s.bus.channel
    with CanBus(interface, channel, s.bus.bitrate) as bus:
        for k, (ident, data) in enumerate(frames):
            if k:
                time.sleep(0.2)
            bus.send(ident, data)
    sent = ", ".join(data.hex().upper() for _, data in frames)
    print(f"sent {command.name} (ID 0x{frames[0][0]:X} data {sent}) on {interface}:{channel}")
    return 0
