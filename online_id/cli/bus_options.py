"""The bus options of the commands that open a CAN bus, named as python-can's own tools name them.

``-i/--interface``, ``-c/--channel`` and ``-b/--bitrate`` (``can.logger``,
``can.player``, ``can.viewer``) override the config's ``bus`` section.
"""

from __future__ import annotations

import argparse
import dataclasses

from online_id.config import Settings
from online_id.errors import ConfigError


def add_bus_options(p: argparse.ArgumentParser) -> None:
    """``-i/--interface``, ``-c/--channel``, ``-b/--bitrate`` (each overrides ``bus.*`` of the config)."""
    p.add_argument("-i", "--interface", help="override bus.interface (a python-can interface: socketcan, virtual ...)")
    p.add_argument("-c", "--channel", help="override bus.channel (e.g. can0, vcan0)")
    p.add_argument("-b", "--bitrate", type=int, metavar="BPS", help="override bus.bitrate (bit/s)")


def with_bus_options(s: Settings, args: argparse.Namespace) -> Settings:
    """``s`` with the bus options of ``args`` applied."""
    over = {k: getattr(args, k, None) for k in ("interface", "channel", "bitrate")}
    over = {k: v for k, v in over.items() if v is not None and v != ""}
    if "bitrate" in over and not over["bitrate"] > 0:
        raise ConfigError(f"--bitrate: expected a number of bit/s > 0, got {over['bitrate']!r}")
    return dataclasses.replace(s, bus=dataclasses.replace(s.bus, **over)) if over else s
