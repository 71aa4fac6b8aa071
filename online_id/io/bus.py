"""The CAN bus adapter: python-can behind one small interface, errors wrapped."""

from __future__ import annotations

import socket
from dataclasses import dataclass

import can

from online_id.errors import BusError


@dataclass(frozen=True)
class Frame:
    """A received or sent CAN frame (python-can's Message, reduced to what we use)."""

    t_s: float
    arbitration_id: int
    data: bytes
    is_extended: bool = False
    is_error: bool = False
    is_remote: bool = False


class CanBus:
    """A python-can bus opened with ``ignore_config=True`` (no ~/can.conf, no CAN_* variables)."""

    def __init__(self, interface: str, channel: str, bitrate: int | None = None,
                 receive_own_messages: bool = False, receive_buffer_bytes: int = 4 << 20, **kwargs) -> None:
        self.interface = interface
        self.channel = channel
        opts = dict(kwargs)
        if bitrate is not None:
            opts["bitrate"] = bitrate
        try:
            self._bus = can.Bus(interface=interface, channel=channel, ignore_config=True,
                                receive_own_messages=receive_own_messages, **opts)
        except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as err:
            raise BusError(f"cannot open CAN bus {interface}:{channel}: {err}") from err
        self.receive_buffer_bytes = self._grow_receive_buffer(receive_buffer_bytes)

    def _grow_receive_buffer(self, size: int) -> int | None:
        """Ask for a large kernel receive buffer on SocketCAN, so a short stall loses no frames.

        SO_RCVBUFFORCE needs CAP_NET_ADMIN; without it SO_RCVBUF is capped by
        ``net.core.rmem_max`` (raise that sysctl on a busy bench).  Returns the
        size the kernel granted, or None for interfaces without a socket.
        """
        sock = getattr(self._bus, "socket", None)
        if sock is None or not size:
            return None
        for option in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
            if option is None:
                continue
            try:
                sock.setsockopt(socket.SOL_SOCKET, option, size)
                break
            except OSError:
                continue
        try:
            return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
        except OSError:
            return None

    def recv(self, timeout: float) -> Frame | None:
        """The next frame, or None after ``timeout`` seconds."""
        try:
            msg = self._bus.recv(timeout)
        except (can.CanError, OSError, ValueError) as err:
            raise BusError(f"CAN bus {self.interface}:{self.channel}: receive failed: {err}") from err
        if msg is None:
            return None
        return Frame(msg.timestamp, msg.arbitration_id, bytes(msg.data), msg.is_extended_id,
                     msg.is_error_frame, msg.is_remote_frame)

    def send(self, arbitration_id: int, data: bytes, is_extended: bool = False, t_s: float | None = None) -> None:
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=is_extended)
        if t_s is not None:
            msg.timestamp = t_s
        try:
            self._bus.send(msg, timeout=0.1)
        except (can.CanError, OSError, ValueError) as err:
            raise BusError(f"CAN bus {self.interface}:{self.channel}: send of ID 0x{arbitration_id:X} failed: {err}") from err

    def close(self) -> None:
        try:
            self._bus.shutdown()
        except (can.CanError, OSError):
            pass

    def __enter__(self) -> "CanBus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
