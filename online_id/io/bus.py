"""The CAN bus adapter: python-can behind one small interface, errors wrapped.

Two things python-can does not give, added here for kernel sockets
(SocketCAN, and the ``udp_multicast`` interface used to test between
processes):

* a receive buffer large enough for a second of traffic (``SO_RCVBUF``,
  or ``SO_RCVBUFFORCE`` as root), so a short stall of the process loses
  nothing;
* the kernel's count of frames dropped because that buffer was full
  (``SO_MEMINFO``: the socket's ``sk_drops``, the counter that SocketCAN's
  ``SO_RXQ_OVFL`` reports per frame), read with :meth:`CanBus.dropped`;
* a send that costs the receive loop little more than the kernel's write:
  python-can's ``send`` builds a ``can.Message`` and packs it anew for every
  frame (10-20 us of the loop's time at a publication, up to 100 us with cold
  caches; on SocketCAN also a ``select`` and two logging calls).  For these
  two backends :class:`_Wire` keeps, per ID and length, the bytes python-can
  itself packs, with the data's place in them, and writes the frame with one
  call: on ``udp_multicast`` through python-can's own sender, on SocketCAN a
  non-blocking write whose full queue falls back to python-can's ``send``
  (which waits up to ``send_timeout_s``).

An open that fails is classified: :class:`BusError` with ``permanent``
set means retrying cannot help (no CAN in the kernel, an interface python-can
does not know, a missing optional package); otherwise the bus may come up
later (an adapter unplugged, ``can0`` down) and the service retries.
"""

from __future__ import annotations

import errno
import socket
import struct
from collections.abc import Mapping
from typing import Any

import can

from online_id.errors import BusError


class Frame:
    """A received or sent CAN frame (python-can's Message, reduced to what we use).

    A plain class with slots, not a dataclass: one is made per received frame.
    """

    __slots__ = ("t_s", "arbitration_id", "data", "is_extended", "is_error", "is_remote")

    def __init__(self, t_s: float, arbitration_id: int, data: bytes, is_extended: bool = False,
                 is_error: bool = False, is_remote: bool = False) -> None:
        self.t_s = t_s
        self.arbitration_id = arbitration_id
        self.data = data
        self.is_extended = is_extended
        self.is_error = is_error
        self.is_remote = is_remote

    def __repr__(self) -> str:
        return f"Frame(t_s={self.t_s!r}, arbitration_id=0x{self.arbitration_id:X}, data={self.data.hex()})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Frame) and all(getattr(self, k) == getattr(other, k) for k in self.__slots__)


SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)  # Linux >= 4.13; Python does not name it
SK_MEMINFO_DROPS = 8  # index of sk_drops in the u32 array SO_MEMINFO returns
_PERMANENT_ERRNOS = {errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT, errno.ESOCKTNOSUPPORT, errno.EACCES, errno.EPERM}


def _open_error(interface: str, channel: str, err: BaseException) -> BusError:
    """A one-line BusError for a failed open, with ``permanent`` set when retrying cannot help, and the fix."""
    text = f"cannot open CAN bus {interface}:{channel}: {err}"
    permanent, hint = False, ""
    if isinstance(err, (ImportError, NotImplementedError)):
        permanent = True
        if "msgpack" in str(err):
            hint = "install the Python package msgpack (pip install msgpack), which this interface needs"
        else:
            hint = f"check bus.interface (python-can interfaces: {', '.join(sorted(can.VALID_INTERFACES))})"
    elif isinstance(err, ValueError):
        permanent, hint = True, "check bus.channel, bus.bitrate and bus.options"
    elif isinstance(err, (TypeError, OverflowError)):  # an argument the interface does not take, or out of range
        permanent, hint = True, "check bus.options against the interface's arguments in python-can's documentation"
    elif isinstance(err, socket.gaierror) and err.errno == socket.EAI_SERVICE:  # a port that is no number
        permanent, hint = True, "check bus.options: a port is a number (0-65535)"
    elif isinstance(err, OSError) and err.errno in _PERMANENT_ERRNOS:
        permanent = True
        hint = ("this kernel has no SocketCAN (AF_CAN): load the can and can-raw modules "
                "(modprobe can-raw), or use another interface" if err.errno == errno.EAFNOSUPPORT
                else "the process may not open this interface: check its permissions")
    error = BusError(f"{text}; {hint}" if hint else text)
    error.permanent = permanent
    return error


def _shut_partial(err: BaseException) -> None:
    """Shut down a bus whose constructor raised ``err`` after python-can's base class had set it up (its
    frames still hold it): else it is collected later with a stray "was not properly shut down" warning
    on stderr, and whatever it had opened stays open until then."""
    tb = err.__traceback__
    while tb is not None:
        obj = tb.tb_frame.f_locals.get("self")
        if isinstance(obj, can.BusABC):
            try:
                obj.shutdown()  # marks it shut down first; the interface's part may fail on what was never made
            except Exception:  # noqa: BLE001 - best effort on a half-made object
                pass
        tb = tb.tb_next


class CanBus:
    """A python-can bus opened with ``ignore_config=True`` (no ~/can.conf, no CAN_* variables).

    ``receive_buffer_bytes``: the kernel receive buffer asked for on socket
    interfaces (8 MiB, which the kernel doubles: about two seconds of a full
    1 Mbit/s bus at ~1 KiB of kernel memory per frame).  ``send_timeout_s``:
    how long a send may block on a full transmit queue before it fails.
    """

    def __init__(self, interface: str, channel: str, bitrate: int | None = None,
                 receive_own_messages: bool = False, receive_buffer_bytes: int = 8 << 20,
                 send_timeout_s: float = 0.1, options: Mapping[str, Any] | None = None, **kwargs) -> None:
        self.interface = interface
        self.channel = channel
        self.send_timeout_s = send_timeout_s
        opts = {**(options or {}), **kwargs}
        if bitrate is not None:
            opts["bitrate"] = bitrate
        try:
            self._bus = can.Bus(interface=interface, channel=channel, ignore_config=True,
                                receive_own_messages=receive_own_messages, **opts)
        except (can.CanError, OSError, ValueError, TypeError, OverflowError, ImportError, NotImplementedError) as err:
            _shut_partial(err)
            raise _open_error(interface, channel, err) from err
        self.receive_buffer_bytes = self._grow_receive_buffer(receive_buffer_bytes)
        self._recv = getattr(self._bus, "_recv_internal", None) or self._recv_generic
        self._wire = _Wire.of(self._bus, self.send_timeout_s)

    def _recv_generic(self, timeout: float):
        return self._bus.recv(timeout), False

    def _socket(self) -> socket.socket | None:
        """The kernel socket under python-can's bus (SocketCAN, udp_multicast), else None."""
        sock = getattr(self._bus, "socket", None)
        if sock is None:
            sock = getattr(getattr(self._bus, "_multicast", None), "_socket", None)
        return sock if isinstance(sock, socket.socket) else None

    def dropped(self) -> int | None:
        """Frames the kernel dropped since the socket opened because its receive buffer was full.

        None where there is no kernel socket (python-can's ``virtual`` bus,
        whose queue is unbounded) or the kernel cannot tell.
        """
        sock = self._socket()
        if sock is None:
            return None
        try:
            raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * (SK_MEMINFO_DROPS + 1))
        except OSError:
            return None
        if len(raw) < 4 * (SK_MEMINFO_DROPS + 1):
            return None
        return int(struct.unpack_from(f"{SK_MEMINFO_DROPS + 1}I", raw)[SK_MEMINFO_DROPS])

    def _grow_receive_buffer(self, size: int) -> int | None:
        """Ask for a large kernel receive buffer on SocketCAN, so a short stall loses no frames.

        SO_RCVBUFFORCE needs CAP_NET_ADMIN; without it SO_RCVBUF is capped by
        ``net.core.rmem_max`` (raise that sysctl on a busy bench).  Returns the
        size the kernel granted, or None for interfaces without a socket.
        """
        sock = self._socket()
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
        """The next frame, or None after ``timeout`` seconds.

        Calls the backend's ``_recv_internal`` (the one method every
        python-can backend implements) rather than ``BusABC.recv``: this bus
        sets no filters, and the generic wrapper's bookkeeping and debug
        logging cost about a tenth of the service's time per frame.
        """
        try:
            msg, _filtered = self._recv(timeout)
        except (can.CanError, OSError, ValueError) as err:
            raise BusError(f"CAN bus {self.interface}:{self.channel}: receive failed: {err}") from err
        if msg is None:
            return None
        return Frame(msg.timestamp, msg.arbitration_id, bytes(msg.data), msg.is_extended_id,
                     msg.is_error_frame, msg.is_remote_frame)

    def send(self, arbitration_id: int, data: bytes, is_extended: bool = False, t_s: float | None = None) -> None:
        """Send one frame (``t_s``: the timestamp a backend carries, as a replayed log's; else none)."""
        if self._wire is not None and t_s is None:
            try:
                if self._wire.send(arbitration_id, data, is_extended):
                    return
            except (can.CanError, OSError, ValueError) as err:
                raise BusError(f"CAN bus {self.interface}:{self.channel}: send of ID 0x{arbitration_id:X} "
                               f"failed: {err}") from err
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=is_extended)
        if t_s is not None:
            msg.timestamp = t_s
        try:
            self._bus.send(msg, timeout=self.send_timeout_s)
        except (can.CanError, OSError, ValueError) as err:
            raise BusError(f"CAN bus {self.interface}:{self.channel}: send of ID 0x{arbitration_id:X} failed: {err}") from err

    def close(self) -> None:
        self._wire = None
        try:
            self._bus.shutdown()
        except (can.CanError, OSError):
            pass

    def __enter__(self) -> "CanBus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Wire:
    """The bytes python-can writes for a classic frame on one kernel-socket backend, packed by python-can once per
    (ID, extended, length) and then filled in (see module notes).

    Each template is python-can's own packing of a probe frame, with the place of the data found by packing
    two probes that differ only in their data; it is used only after a third probe with other data packs
    exactly as python-can packs it (else that ID and length always take python-can's ``send``).
    """

    __slots__ = ("_pack", "_write", "_templates")

    def __init__(self, pack, write) -> None:
        self._pack = pack  # python-can's packing: can.Message -> the bytes its send writes
        self._write = write  # bytes -> True when written, False when python-can's send must write them
        self._templates: dict[tuple[int, bool, int], tuple[bytes, bytes] | None] = {}

    @classmethod
    def of(cls, bus: can.BusABC, timeout_s: float) -> "_Wire | None":
        """The writer for ``bus`` (None for a backend without one: python-can's ``send`` serves)."""
        try:
            from can.interfaces.socketcan import SocketcanBus
            from can.interfaces.socketcan.socketcan import build_can_frame
            from can.interfaces.udp_multicast import UdpMulticastBus
            from can.interfaces.udp_multicast.utils import pack_message
        except ImportError:
            return None
        if isinstance(bus, UdpMulticastBus):
            sender = getattr(bus, "_multicast", None)
            if sender is None or not hasattr(sender, "send") or getattr(bus, "_can_protocol", None) is None:
                return None
            return cls(pack_message, lambda wire: sender.send(wire, timeout_s) or True)
        if isinstance(bus, SocketcanBus) and isinstance(getattr(bus, "socket", None), socket.socket) and bus.channel:
            sock = bus.socket

            def write(wire: bytes) -> bool:
                try:
                    return sock.send(wire, socket.MSG_DONTWAIT) == len(wire)
                except (BlockingIOError, InterruptedError):
                    return False  # the transmit queue is full: python-can's send waits for it
                except OSError as err:
                    if err.errno == errno.ENOBUFS:
                        return False
                    raise

            return cls(build_can_frame, write)
        return None

    def _template(self, key: tuple[int, bool, int]) -> tuple[bytes, bytes] | None:
        ident, extended, n = key
        try:
            probes = [self._pack(can.Message(arbitration_id=ident, is_extended_id=extended, data=bytes([b] * n)))
                      for b in (0x00, 0xFF)]
        except (can.CanError, ValueError, TypeError):
            return None
        a, b = probes
        diff = [k for k in range(min(len(a), len(b))) if a[k] != b[k]]
        if len(a) != len(b) or len(diff) != n or (n and diff != list(range(diff[0], diff[0] + n))):
            return None
        at = diff[0] if n else len(a)
        if n == 0 and a != b:
            return None
        template = (a[:at], a[at + n:])
        check = bytes((37 * k + 11) & 0xFF for k in range(n))
        if template[0] + check + template[1] != self._pack(can.Message(arbitration_id=ident, is_extended_id=extended,
                                                                       data=check)):
            return None
        return template

    def send(self, arbitration_id: int, data: bytes, is_extended: bool) -> bool:
        """Write the frame; False where python-can's ``send`` must (no template, or the queue full)."""
        key = (arbitration_id, is_extended, len(data))
        try:
            template = self._templates[key]
        except KeyError:
            template = self._templates[key] = self._template(key)
        if template is None:
            return False
        return self._write(template[0] + bytes(data) + template[1])
