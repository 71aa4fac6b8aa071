"""Structured journald entries through the native protocol (no dependency).

``send(MESSAGE=..., PRIORITY=..., FAULT_CODE=..., FREQ_DRIFT_PCT=...)`` writes
one entry to ``/run/systemd/journal/socket``; without journald it does
nothing (the service also logs a plain line on stderr, which systemd
forwards to the journal anyway, without the fields).
"""

from __future__ import annotations

import os
import socket
import struct

SOCKET_PATH = "/run/systemd/journal/socket"


def _field(key: str, value: object) -> bytes:
    data = str(value).encode()
    if b"\n" in data:
        # binary-safe form: KEY\n<64-bit little-endian length><data>\n
        return key.encode() + b"\n" + struct.pack("<Q", len(data)) + data + b"\n"
    return key.encode() + b"=" + data + b"\n"


def encode_entry(fields: dict[str, object]) -> bytes:
    """The datagram journald expects for one entry (keys upper case, as journald requires)."""
    return b"".join(_field(k.upper(), v) for k, v in fields.items() if v is not None)


class Journal:
    """Sends entries to journald when its socket exists."""

    def __init__(self, path: str = SOCKET_PATH, identifier: str = "online-id") -> None:
        self.path = path
        self.identifier = identifier
        self._sock = None
        if os.path.exists(path):
            try:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            except OSError:
                self._sock = None

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, message: str, priority: int = 6, **fields: object) -> bool:
        """One structured entry; returns False when journald is not there or refused it."""
        if self._sock is None:
            return False
        entry = encode_entry({"MESSAGE": message, "PRIORITY": priority, "SYSLOG_IDENTIFIER": self.identifier,
                              **fields})
        try:
            self._sock.sendto(entry, self.path)
            return True
        except OSError:
            return False
