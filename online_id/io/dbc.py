"""DBC codec: input frames -> :class:`~online_id.records.SignalSample`, publications -> frames.

The default database is ``online_id/data/online_id.dbc`` (the repository's
``dbc/online_id.dbc`` is a link to it: one file).  A bench with its own DBC maps
its messages and signals onto the three input roles with a :class:`RoleMapping`.

Every input frame given to :meth:`InputDecoder.decode` ends in exactly one of

* a list of :class:`~online_id.records.SignalSample` (SI units, sign applied),
* a :class:`CommandSample` (the ``OidCommand`` frame),
* a :class:`~online_id.records.FrameFault` (the frame is not used).

Checks of the frames' integrity, as far as CAN allows:

* A message whose mapping names a CRC signal (``RoleSignal.crc``,
  ``CommandSignal.crc``) must carry in byte 7 the CRC-8 SAE J1850 of bytes
  0..6 (:mod:`online_id.io.crc`); else ``BAD_CRC`` (inputs) or
  ``COMMAND_REFUSED`` (the command).  The command's CRC is on by default,
  the inputs' is optional (``mapping.<role>.crc``).
* A command with a non-finite timestamp is ``COMMAND_REFUSED``.

A CRC is no signature: any node on the bus can compute it.  It catches
corrupt and random frames.  A command's freshness value and MAC (the
``CommandFreshness`` and ``CommandMac`` signals, :mod:`online_id.io.auth`)
are read here and judged by :mod:`online_id.service.commands`, which keeps the
freshness and the key, with what a command may do.

Output frames: :class:`~online_id.io.dbc_output.OutputEncoder` (that module imports this one, never
the reverse).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import cantools
import numpy as np

from online_id.errors import ConfigError, DbcError, InputDataError, printable
from online_id.io.auth import command_mac
from online_id.io.crc import crc8_j1850
from online_id.records import ROLES, FrameFault, SignalSample

RAD_S_PER_RPM = math.pi / 30.0
SPEED_UNITS = ("rpm", "rad/s")
TORQUE_UNITS = ("Nm",)
# DBC unit spellings we recognise; an unknown spelling is accepted as is.
_UNIT_ALIASES = {
    "rpm": "rpm", "1/min": "rpm", "u/min": "rpm", "min-1": "rpm", "r/min": "rpm", "rev/min": "rpm",
    "rad/s": "rad/s", "nm": "Nm", "n.m": "Nm", "n*m": "Nm", "n m": "Nm",
}


def default_dbc_path() -> Path:
    """The DBC shipped inside the package (``dbc/online_id.dbc`` in the repository links to it)."""
    return Path(__file__).resolve().parent.parent / "data" / "online_id.dbc"


def load_dbc(path: str | Path | None = None) -> Any:
    """Load a DBC file strictly (``cantools.database.load_file(..., strict=True)``).

    ``None`` loads :func:`default_dbc_path`.  Raises :class:`DbcError` with a
    one-line message naming the file (and the line, for syntax errors).
    """
    path = Path(path) if path is not None else default_dbc_path()
    try:
        return cantools.database.load_file(str(path), strict=True)
    except OSError as err:
        raise DbcError(f"{path}: cannot read the DBC file: {err.strerror or err}") from err
    except (cantools.database.Error, ValueError, KeyError, IndexError) as err:
        text = printable(" ".join(str(err).split()))
        m = re.search(r'Invalid syntax at line (\d+), column (\d+): "(.*)"', text)
        if m:
            raise DbcError(
                f"{path}:{m.group(1)}: invalid DBC syntax at column {m.group(2)} "
                f"(marked >>!<<): {m.group(3).strip()}"
            ) from err
        text = re.sub(r'^DBC: "(.*)"$', r"\1", text)
        raise DbcError(f"{path}: not a usable DBC file: {text}") from err


# --- role mapping ---------------------------------------------------------------------


@dataclass(frozen=True)
class RoleSignal:
    """Where one input role lives in the DBC and how to bring it to SI units.

    ``unit``: ``"rpm"`` or ``"rad/s"`` for speeds, ``"Nm"`` for torque.
    ``sign``: +1, or -1 when the bench's positive direction is the opposite of
    ours (torque: positive = braking).  ``counter``: alive counter signal or None.
    """

    message: str
    signal: str
    unit: str
    sign: int = 1
    counter: str | None = None
    crc: str | None = None

    def __post_init__(self) -> None:
        if self.sign not in (1, -1):
            raise ConfigError(f'Expected sign +1 or -1 for signal "{self.signal}", but got {self.sign!r}.')


@dataclass(frozen=True)
class CommandSignal:
    """Where the service command lives in the DBC: the command, its freshness value (the low bits of it),
    its MAC (authenticated mode) and its CRC."""

    message: str = "OidCommand"
    signal: str = "Command"
    freshness: str | None = "CommandFreshness"
    mac: str | None = "CommandMac"
    crc: str | None = "OidCommandCRC"


@dataclass(frozen=True)
class RoleMapping:
    """Message and signal of each role in :data:`~online_id.records.ROLES` (default: online_id.dbc)."""

    dyno_speed: RoleSignal = RoleSignal("DynoSpeed", "DynoSpeed", "rpm", 1, "DynoSpeedCounter")
    engine_speed: RoleSignal = RoleSignal("EngineSpeed", "EngineSpeed", "rpm", 1, "EngineSpeedCounter")
    dyno_torque: RoleSignal = RoleSignal("DynoTorque", "DynoTorque", "Nm", 1, "DynoTorqueCounter")
    command: CommandSignal | None = field(default_factory=CommandSignal)

    def __post_init__(self) -> None:
        for role in ROLES:
            rs = getattr(self, role)
            allowed = TORQUE_UNITS if role == "dyno_torque" else SPEED_UNITS
            if rs.unit not in allowed:
                raise ConfigError(
                    f"Expected unit {' or '.join(repr(u) for u in allowed)} for role {role} "
                    f'(signal "{rs.signal}"), but got {rs.unit!r}.'
                )

    def role(self, name: str) -> RoleSignal:
        """The :class:`RoleSignal` of role ``name``."""
        if name not in ROLES:
            raise ConfigError(f"Expected a role in {', '.join(ROLES)}, but got {name!r}.")
        return getattr(self, name)


class BenchCommand(IntEnum):
    """Values of the ``Command`` signal of ``OidCommand``."""

    NONE = 0
    ACK_ALERT = 1
    RELEARN_BASELINE = 2
    RESET_ESTIMATOR = 3


@dataclass(frozen=True)
class CommandSample:
    """A command frame received at ``t_s``: its freshness value's low bits and its MAC bytes, as sent."""

    command: BenchCommand
    t_s: float
    freshness: int | None = None
    mac: bytes | None = None


# --- DBC look-ups with errors that list what exists ------------------------------------


def _message(db: Any, name: str, source: str, what: str) -> Any:
    try:
        return db.get_message_by_name(name)
    except KeyError:
        have = ", ".join(sorted(m.name for m in db.messages)) or "none"
        raise DbcError(f'{source}: expected a message "{name}" ({what}), but the DBC has: {have}.') from None


def _signal(msg: Any, name: str, source: str, what: str) -> Any:
    try:
        return msg.get_signal_by_name(name)
    except KeyError:
        have = ", ".join(s.name for s in msg.signals) or "none"
        raise DbcError(
            f'{source}: expected a signal "{name}" ({what}) in message "{msg.name}", but it has: {have}.'
        ) from None


def _mac_signal(msg: Any, name: str, source: str) -> int:
    """Check that signal ``name`` of ``msg`` can hold a truncated MAC (whole bytes, 3 to 8, little-endian
    unsigned, on byte boundaries: its bytes are the MAC's, in order); returns its length in bits."""
    sig = _signal(msg, name, source, "MAC of the command")
    if sig.length % 8 or not 24 <= sig.length <= 64 or sig.start % 8 or sig.byte_order != "little_endian" \
            or sig.is_signed or sig.is_float:
        raise DbcError(f'{source}: expected signal "{name}" in message "{msg.name}" to be 3 to 8 whole bytes, '
                       f"unsigned little-endian from a byte boundary (the MAC's bytes in order), but got start "
                       f"{sig.start} length {sig.length} {sig.byte_order}.")
    return int(sig.length)


def _crc_signal(msg: Any, name: str, source: str) -> None:
    """Check that signal ``name`` of ``msg`` is an 8-bit CRC filling byte 7 of an 8-byte frame."""
    sig = _signal(msg, name, source, "CRC-8 over bytes 0..6")
    start = 56 if sig.byte_order == "little_endian" else 63
    if msg.length != 8 or sig.length != 8 or sig.start != start:
        raise DbcError(f'{source}: expected message "{msg.name}" of 8 bytes with signal "{name}" filling byte 7, '
                       f"but got length {msg.length}, signal start {sig.start} length {sig.length}.")


def _scaling(sig: Any) -> tuple[float, float, float]:
    scale, offset = float(sig.scale), float(sig.offset)
    inv = 1.0 / scale if scale else 0.0
    divisor = round(inv) if inv and abs(inv - round(inv)) < 1e-9 * abs(inv) else 0.0
    return scale, float(divisor), offset


def _limits(sig: Any) -> str:
    return f"[{'-inf' if sig.minimum is None else sig.minimum}, {'inf' if sig.maximum is None else sig.maximum}]"


def _bounds(sig: Any) -> tuple[float, float]:
    """Physical [min, max] widened by half a resolution step (float rounding of raw*scale)."""
    tol = 0.5 * abs(float(sig.scale)) if not sig.is_float else 0.0
    lo = -math.inf if sig.minimum is None else float(sig.minimum) - tol
    hi = math.inf if sig.maximum is None else float(sig.maximum) + tol
    return lo, hi


signal_bounds = _bounds
"""The physical range a cantools signal allows, widened by half a resolution step (for other modules)."""


# --- input decoding ---------------------------------------------------------------------


@dataclass(frozen=True)
class _RolePlan:
    role: str
    signal: str
    lo: float
    hi: float
    factor: float  # DBC unit -> SI, sign included
    counter: str | None
    is_float: bool
    scale: float
    divisor: float  # 1/scale when that is an integer (exact decimal scaling), else 0
    offset: float
    limits: str = ""  # the DBC's [min, max], for messages

    def physical(self, raw: float) -> float:
        """Raw -> DBC physical value; ``raw / 10000`` rather than ``raw * 0.0001`` so that
        decimal values round-trip exactly (both are the double nearest to the decimal)."""
        if self.divisor:
            return raw / self.divisor + self.offset
        return raw * self.scale + self.offset


@dataclass(frozen=True)
class _FramePlan:
    message: str
    length: int
    decode: Any  # bound cantools Message.decode
    roles: tuple[_RolePlan, ...]
    command: _RolePlan | None
    crc: bool = False  # byte 7 is a CRC-8 of bytes 0..6, to check


class InputDecoder:
    """Decode bench input frames into SI samples; never raises on frame content.

    Parameters
    ----------
    db
        A cantools database (see :func:`load_dbc`).
    mapping
        Where each role lives; default: the messages of online_id.dbc.
    source
        The DBC file name, used in error messages.

    Attributes
    ----------
    last_fault
        Text describing the last fault other than ``UNKNOWN_ID`` (for logs).
    """

    def __init__(self, db: Any, mapping: RoleMapping | None = None, *, source: str = "the DBC") -> None:
        self.mapping = mapping or RoleMapping()
        self.source = source
        self.last_fault = ""
        grouped: dict[str, list[_RolePlan]] = {}
        messages: dict[str, Any] = {}
        with_crc: set[str] = set()
        self.command_freshness_bits = 0  # the width of the command's freshness signal (0: none mapped)
        self.command_mac_bytes = 0  # the bytes of the command's MAC signal (0: none mapped)
        self._command_mac: str | None = None
        for role in ROLES:
            rs = self.mapping.role(role)
            what = f"role {role}"
            msg = _message(db, rs.message, source, what)
            sig = _signal(msg, rs.signal, source, what)
            dbc_unit = _UNIT_ALIASES.get((sig.unit or "").strip().lower())
            if dbc_unit is not None and dbc_unit != rs.unit:
                raise DbcError(
                    f'{source}: expected unit {rs.unit!r} for signal "{sig.name}" in message "{msg.name}" '
                    f"(role {role}), but the DBC says {sig.unit!r}; fix the unit in the role mapping."
                )
            if rs.counter is not None:
                _signal(msg, rs.counter, source, f"alive counter of role {role}")
            if rs.crc is not None:
                _crc_signal(msg, rs.crc, source)
                with_crc.add(msg.name)
            factor = (RAD_S_PER_RPM if rs.unit == "rpm" else 1.0) * rs.sign
            grouped.setdefault(msg.name, []).append(
                _RolePlan(role, sig.name, *_bounds(sig), factor, rs.counter, bool(sig.is_float), *_scaling(sig),
                          _limits(sig))
            )
            messages[msg.name] = msg
        command = None
        if self.mapping.command is not None:
            cs = self.mapping.command
            msg = _message(db, cs.message, source, "service command")
            sig = _signal(msg, cs.signal, source, "service command")
            if cs.freshness is not None:
                self.command_freshness_bits = _signal(msg, cs.freshness, source, "freshness of the command").length
            if cs.mac is not None:
                self.command_mac_bytes = _mac_signal(msg, cs.mac, source) // 8
                self._command_mac = cs.mac
            if cs.crc is not None:
                _crc_signal(msg, cs.crc, source)
                with_crc.add(msg.name)
            command = _RolePlan("command", sig.name, *_bounds(sig), 1.0, cs.freshness, bool(sig.is_float),
                                *_scaling(sig), _limits(sig))
            messages.setdefault(msg.name, msg)
        self._plans: dict[tuple[int, bool], _FramePlan] = {}
        for name, msg in messages.items():
            is_cmd = command is not None and name == self.mapping.command.message
            if is_cmd and name in grouped:
                raise DbcError(f'{source}: message "{name}" carries both input roles and the command; '
                               f"expected separate messages.")
            self._plans[(int(msg.frame_id), bool(msg.is_extended_frame))] = _FramePlan(
                name, int(msg.length), msg.decode, tuple(grouped.get(name, ())), command if is_cmd else None,
                name in with_crc,
            )

    @property
    def frame_ids(self) -> dict[int, bool]:
        """Arbitration IDs of the input frames and whether each is extended (for bus filters)."""
        return {fid: ext for fid, ext in self._plans}

    def _fault(self, kind: FrameFault, text: str) -> FrameFault:
        self.last_fault = text
        return kind

    def decode(
        self, arbitration_id: int, data: bytes | bytearray | None, t_s: float, is_extended: bool = False
    ) -> list[SignalSample] | CommandSample | FrameFault:
        """Decode one frame: samples (one per role it carries), a command, or why it is not used."""
        plan = self._plans.get((arbitration_id, bool(is_extended)))
        if plan is None:
            return FrameFault.UNKNOWN_ID
        n = 0 if data is None else len(data)
        if n != plan.length:
            return self._fault(FrameFault.BAD_DLC,
                               f'message "{plan.message}": expected {plan.length} data bytes, but got {n}')
        if plan.crc and crc8_j1850(data[:7]) != data[7]:
            return self._fault(FrameFault.COMMAND_REFUSED if plan.command is not None else FrameFault.BAD_CRC,
                               f'message "{plan.message}": CRC 0x{data[7]:02X} in byte 7 does not match bytes 0..6 '
                               f"(expected 0x{crc8_j1850(data[:7]):02X})")
        try:
            values = plan.decode(data if type(data) is bytes else bytes(data), False, False)
        except Exception as err:  # noqa: BLE001 - third-party decoder fed arbitrary bytes
            return self._fault(FrameFault.MALFORMED, f'message "{plan.message}": cannot decode: {err}')
        if plan.command is not None:
            return self._decode_command(plan, values, t_s)
        samples = []
        for rp in plan.roles:
            raw = values.get(rp.signal)
            if raw is None:  # multiplexed message, other page
                continue
            value = rp.physical(raw)
            if rp.is_float and not math.isfinite(value):
                return self._fault(FrameFault.NOT_FINITE,
                                   f'signal "{rp.signal}" in message "{plan.message}": got {value}')
            if not rp.lo <= value <= rp.hi:
                return self._fault(FrameFault.OUT_OF_RANGE, self._range_text(rp, plan, value))
            counter = values.get(rp.counter) if rp.counter is not None else None
            samples.append(SignalSample(rp.role, value * rp.factor, t_s, None if counter is None else int(counter)))
        return samples

    def _decode_command(self, plan: _FramePlan, values: dict, t_s: float) -> CommandSample | FrameFault:
        rp = plan.command
        value = rp.physical(values[rp.signal])
        if not math.isfinite(value):
            return self._fault(FrameFault.NOT_FINITE, f'signal "{rp.signal}" in message "{plan.message}": got {value}')
        if not rp.lo <= value <= rp.hi or value not in BenchCommand._value2member_map_:
            return self._fault(FrameFault.OUT_OF_RANGE, self._range_text(rp, plan, value))
        if not math.isfinite(t_s):
            return self._fault(FrameFault.COMMAND_REFUSED, f'message "{plan.message}": timestamp {t_s} is not finite')
        freshness = values.get(rp.counter) if rp.counter is not None else None  # the command plan's "counter"
        mac = None
        if self._command_mac is not None:
            mac = int(values[self._command_mac]).to_bytes(self.command_mac_bytes, "little")
        return CommandSample(BenchCommand(int(value)), t_s, None if freshness is None else int(freshness), mac)

    @staticmethod
    def _range_text(rp: _RolePlan, plan: _FramePlan, value: float) -> str:
        return (f'Expected signal "{rp.signal}" value in {rp.limits} in message '
                f'"{plan.message}", but got {value!r}')


# --- input encoding (bench samples -> frames) ---------------------------------------------


def _fill_value(sig: Any) -> float:
    lo, hi = _bounds(sig)
    return min(max(0.0, lo), hi)


def encode_inputs(
    time_s: Sequence[float] | np.ndarray,
    dyno_speed_rpm: Sequence[float] | np.ndarray,
    engine_speed_rpm: Sequence[float] | np.ndarray,
    dyno_torque_nm: Sequence[float] | np.ndarray,
    *,
    db: Any = None,
    mapping: RoleMapping | None = None,
    decimation: Mapping[str, int] | None = None,
    jitter_s: float = 0.0,
    seed: int = 0,
    source: str = "the bench data",
) -> list[tuple[float, int, bytes]]:
    """Encode bench samples (CSV units: rpm, Nm positive = braking) into input frames.

    Parameters
    ----------
    db, mapping
        Database (default: :func:`load_dbc`) and role mapping (default: online_id.dbc).
    decimation
        Per role, send every k-th sample (``{"dyno_torque": 1, "engine_speed": 2}``);
        roles that share a message must use the same factor.  Default 1.
    jitter_s
        Each frame is delayed by a uniform random ``[0, jitter_s)`` (bus latency);
        keep it below the frame period so that a role's frames stay in order.
    seed
        Seed of the jitter generator.

    Returns
    -------
    list of (t_s, arbitration_id, data)
        Sorted by time; each message has its alive counter (wrapping at its width).

    Raises
    ------
    InputDataError
        A value lies outside its DBC signal range (names the sample and the signal).
    """
    db = db if db is not None else load_dbc()
    mapping = mapping or RoleMapping()
    decimation = dict(decimation or {})
    for role, k in decimation.items():
        if role not in ROLES or not isinstance(k, (int, np.integer)) or k < 1:
            raise ConfigError(f"Expected decimation {{role: integer >= 1}} with roles in {', '.join(ROLES)}, "
                              f"but got {role!r}: {k!r}.")
    if not (math.isfinite(jitter_s) and jitter_s >= 0.0):
        raise ConfigError(f"Expected jitter_s >= 0, but got {jitter_s!r}.")
    t = np.asarray(time_s, dtype=float)
    columns = {"dyno_speed": dyno_speed_rpm, "engine_speed": engine_speed_rpm, "dyno_torque": dyno_torque_nm}
    groups: dict[str, dict[str, np.ndarray]] = {}
    steps: dict[str, int] = {}
    counters: dict[str, str | None] = {}
    crcs: set[str] = set()
    for role in ROLES:
        rs = mapping.role(role)
        msg = _message(db, rs.message, "DBC", f"role {role}")
        sig = _signal(msg, rs.signal, "DBC", f"role {role}")
        x = np.asarray(columns[role], dtype=float)
        if x.shape != t.shape:
            raise InputDataError(f"{source}: {role} has {x.size} samples but time has {t.size}")
        x = (x * RAD_S_PER_RPM if rs.unit == "rad/s" else x) * rs.sign
        lo, hi = _bounds(sig)
        bad = np.flatnonzero(~((x >= lo) & (x <= hi)))
        if bad.size:
            i = int(bad[0])
            raise InputDataError(
                f'{source}: sample {i} (t = {t[i]:g} s): expected signal "{sig.name}" value in '
                f'{_limits(sig)} {sig.unit or ""} in message "{msg.name}", but got {x[i]!r}'
            )
        k = int(decimation.get(role, 1))
        if steps.setdefault(msg.name, k) != k:
            raise ConfigError(f'Expected one decimation for the roles in message "{msg.name}", '
                              f"but got {steps[msg.name]} and {k}.")
        groups.setdefault(msg.name, {})[sig.name] = x
        if rs.counter is not None:
            counters[msg.name] = rs.counter
        if rs.crc is not None:
            _crc_signal(msg, rs.crc, "DBC")
            crcs.add(msg.name)
    rng = np.random.default_rng(seed)
    frames: list[tuple[float, int, bytes]] = []
    for name, signals in groups.items():
        msg = db.get_message_by_name(name)
        idx = np.arange(0, t.size, steps[name])
        times = t[idx] + (rng.uniform(0.0, jitter_s, idx.size) if jitter_s > 0 else 0.0)
        counter = counters.get(name)
        wrap = 1 << msg.get_signal_by_name(counter).length if counter else 1
        base = {s.name: _fill_value(s) for s in msg.signals if s.name not in signals}
        cols = {s: v[idx].tolist() for s, v in signals.items()}
        encode, fid, crc = msg.encode, int(msg.frame_id), name in crcs
        for j, tj in enumerate(times.tolist()):
            values = dict(base)
            for s, v in cols.items():
                values[s] = v[j]
            if counter:
                values[counter] = j % wrap
            data = bytes(encode(values, scaling=True, padding=False, strict=False))
            frames.append((tj, fid, data[:7] + bytes([crc8_j1850(data[:7])]) if crc else data))
    frames.sort(key=lambda f: f[0])
    return frames


def encode_command(db: Any, message: str, signal: str, command: int, freshness: int = 0,
                   crc: str | None = "OidCommandCRC", *, key: bytes | None = None,
                   freshness_signal: str | None = "CommandFreshness",
                   mac_signal: str | None = "CommandMac") -> tuple[int, bytes]:
    """The service command frame ``(arbitration_id, data)``: the command, the low bits of the 32-bit
    ``freshness`` value, with ``key`` its MAC (:func:`online_id.io.auth.command_mac`; without, 0), other signals
    0, and byte 7 the CRC-8 of bytes 0..6 when the message has signal ``crc``."""
    msg = _message(db, message, "the DBC", "service command")
    _signal(msg, signal, "the DBC", "service command")
    names = {s.name for s in msg.signals}
    values = {s.name: 0 for s in msg.signals}
    values[signal] = int(command)
    if freshness_signal in names:
        values[freshness_signal] = int(freshness) % (1 << msg.get_signal_by_name(freshness_signal).length)
    if key is not None:
        if mac_signal not in names:
            raise DbcError(f'Cannot authenticate command {command}: message "{message}" has no MAC signal '
                           f'"{mac_signal}".')
        n_bytes = _mac_signal(msg, mac_signal, "the DBC") // 8
        mac = command_mac(key, int(msg.frame_id), int(command), int(freshness), n_bytes)
        values[mac_signal] = int.from_bytes(mac, "little")
    try:
        data = bytes(msg.encode(values, scaling=True, padding=True, strict=True))
    except (cantools.database.Error, ValueError, KeyError) as err:
        raise DbcError(f'Cannot encode command {command} in message "{message}": {err}') from err
    if crc is not None and crc in names:
        _crc_signal(msg, crc, "the DBC")
        data = data[:7] + bytes([crc8_j1850(data[:7])])
    return int(msg.frame_id), data
