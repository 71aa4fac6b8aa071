"""systemd notification protocol (sd_notify) without a dependency.

Sends ``READY=1``, ``STATUS=...``, ``WATCHDOG=1`` and ``STOPPING=1`` datagrams to
``$NOTIFY_SOCKET`` when the service runs under systemd with ``Type=notify``;
does nothing otherwise.
"""

from __future__ import annotations

import os
import socket


class Notifier:
    """Talks to systemd when ``$NOTIFY_SOCKET`` is set."""

    def __init__(self) -> None:
        addr = os.environ.get("NOTIFY_SOCKET")
        self._sock = None
        self._addr = None
        if addr:
            if addr.startswith("@"):
                addr = "\0" + addr[1:]  # abstract namespace
            self._addr = addr
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        self.watchdog_s = None
        if usec and (pid is None or pid == str(os.getpid())):
            try:
                self.watchdog_s = int(usec) / 1e6
            except ValueError:
                self.watchdog_s = None

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, text: str) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(text.encode(), self._addr)
        except OSError:
            pass  # systemd went away: nothing useful to do

    def ready(self, status: str = "") -> None:
        self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, status: str) -> None:
        self.notify(f"STATUS={status}")

    def watchdog(self) -> None:
        self.notify("WATCHDOG=1")

    def stopping(self) -> None:
        self.notify("STOPPING=1")
