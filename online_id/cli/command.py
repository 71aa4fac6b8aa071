"""``online-id ack`` and ``online-id relearn``: send a command frame to the running service.

The service listens for the ``OidCommand`` frame on its bus (a bench PC or
operator panel can send the same frame); these commands open the bus of the
configuration, send the frame once and exit.
"""

from __future__ import annotations

import argparse

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
    ident, data = encode_command(db, s.mapping.command_message, s.mapping.command_signal, command)
    interface = args.interface or s.bus.interface
    channel = args.channel or s.bus.channel
    with CanBus(interface, channel, s.bus.bitrate) as bus:
        bus.send(ident, data)
    print(f"sent {command.name} (ID 0x{ident:X} data {data.hex().upper()}) on {interface}:{channel}")
    return 0
