"""Output frames: publications -> ``(arbitration_id, data)`` with alive counter and CRC-8.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cantools

from online_id.errors import ConfigError, DbcError
from online_id.io.crc import crc8_j1850
from online_id.io.dbc import _message, _signal, load_dbc, signal_bits
from online_id.records import AlertOut, EstimateOut, ExcitationOut, FreshnessOut, Publication, QualityOut, StatusOut

OUTPUT_MESSAGES = {
    "estimate": "OidEstimate",
    "shaft": "OidShaft",
    "quality": "OidQuality",
    "status": "OidStatus",
    "alert": "OidAlert",
    "excitation": "OidExcitation",
    "freshness": "OidFreshness",
}
"""Default message name of each output (key -> DBC message)."""
OPTIONAL_OUTPUTS = ("freshness",)
"""Outputs a DBC may lack (a bench's DBC from before them): never sent then."""


_REHEARSAL = {"ResonanceFreq": 20.0, "DampingRatio": 0.05, "Valid": True}  # see OutputEncoder.rehearse
VALUE, COUNTER, CRC = 0, 1, 2
"""What a :class:`_Packer` field carries: a physical value, the alive counter, the CRC (0 until computed)."""


class _Packer:
    """One output message's signals packed straight into the frame's bits, as cantools packs them.

    The receive loop owes the bus an OidEstimate within a fraction of a millisecond; ``Message.encode``
    spends 20-40 us per frame in its generic machinery (signal dictionaries, bitstruct formats for both
    byte orders, padding masks).  Here each value is clamped as :meth:`OutputEncoder._encode` clamps it,
    its raw value comes from its signal's own cantools conversion (``numeric_scaled_to_raw``, the call
    cantools makes) and goes to the bit positions cantools gives it, found once by encoding every bit
    of every signal with cantools itself; a signal whose bits lie in order (every little-endian one) is
    one shift and mask.  :meth:`pack` returns None where it cannot give exactly what cantools would (a
    raw value its bits cannot hold); the caller then lets cantools encode and report it.  Messages with
    a float or a multiplexed signal have no packer (:func:`_packer` returns None).
    """

    __slots__ = ("values", "counter")

    def __init__(self, fields: tuple) -> None:
        # per signal: (name, what, lo, hi, to_raw, lo_raw, hi_raw, shift, mask, bit positions or None); the CRC's
        # bits are left 0 (the caller writes byte 7)
        self.values = tuple(f for f in fields if f[1] == VALUE)
        self.counter = next((f for f in fields if f[1] == COUNTER), None)

    def pack(self, values: Mapping[str, float], count: int) -> int | None:
        """The frame with alive counter ``count`` and a zero CRC as a little-endian integer (byte k is
        bits 8k..8k+7), None where cantools must encode it."""
        word = 0
        isfinite = math.isfinite
        for name, _what, lo, hi, to_raw, lo_raw, hi_raw, shift, mask, bits in self.values:
            v = float(values.get(name, 0.0))
            raw = to_raw((lo if v < lo else hi if v > hi else v) if isfinite(v) else min(max(0.0, lo), hi))
            if not lo_raw <= raw <= hi_raw:
                return None
            if bits is None:
                word |= (raw & mask) << shift  # (& mask: two's complement of a negative raw value)
            else:
                word |= _scatter(raw & mask, bits)
        if self.counter is not None:
            _name, _what, _lo, _hi, to_raw, lo_raw, hi_raw, shift, mask, bits = self.counter
            raw = to_raw(count)
            if not lo_raw <= raw <= hi_raw:
                return None
            word |= (raw & mask) << shift if bits is None else _scatter(raw & mask, bits)
        return word


def _scatter(raw: int, bits: tuple[int, ...]) -> int:
    """Bit k of ``raw`` at bit ``bits[k]``."""
    word = 0
    for k, pos in enumerate(bits):
        if raw >> k & 1:
            word |= 1 << pos
    return word


def _packer(message: Any, counter: str, crc: str, bounds: Mapping[str, tuple[float, float]]) -> _Packer | None:
    """The fast packer of ``message`` (see :class:`_Packer`), None where cantools must encode it."""
    fields = []
    for sig in message.signals:
        positions = signal_bits(message, sig)
        if positions is None:
            return None
        n = len(positions)
        lo_raw, hi_raw = ((-(1 << (n - 1)), (1 << (n - 1)) - 1) if sig.is_signed else (0, (1 << n) - 1))
        in_order = positions == tuple(range(positions[0], positions[0] + n))
        what = COUNTER if sig.name == counter else CRC if sig.name == crc else VALUE
        fields.append((sig.name, what, *bounds[sig.name], sig.conversion.numeric_scaled_to_raw, lo_raw, hi_raw,
                       positions[0] if in_order else 0, (1 << n) - 1, None if in_order else positions))
    return _Packer(tuple(fields))


@dataclass(frozen=True)
class _OutSpec:
    message: Any
    counter: str
    crc: str
    wrap: int
    bounds: dict[str, tuple[float, float]]
    packer: _Packer | None = None
    frame_id: int = 0


def _estimate_values(pub: EstimateOut) -> dict[str, float]:
    """The OidEstimate's signal values of ``pub`` (not valid where a value is not finite)."""
    ok = bool(pub.valid) and math.isfinite(pub.f0_hz) and math.isfinite(pub.zeta)
    return {"ResonanceFreq": pub.f0_hz, "DampingRatio": pub.zeta, "Valid": ok}


def _same(values: Mapping[str, float]) -> tuple:
    """``values`` as a key that equal values (NaN included) give alike."""
    return tuple(v if v == v else None for v in values.values())


def _encodable_range(sig: Any) -> tuple[float, float]:
    """The physical values ``sig`` can carry: its DBC minimum and maximum within what its raw bits hold."""
    lo = float(sig.minimum) if sig.minimum is not None else -math.inf
    hi = float(sig.maximum) if sig.maximum is not None else math.inf
    if not sig.is_float:
        raw_lo, raw_hi = ((-(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1) if sig.is_signed
                          else (0, (1 << sig.length) - 1))
        ends = sorted(float(sig.offset) + float(sig.scale) * r for r in (raw_lo, raw_hi))
        lo, hi = max(lo, ends[0]), min(hi, ends[1])
    return lo, hi


class OutputEncoder:
    """Encode publications into output frames with alive counter and CRC-8 SAE J1850.

    Every output message has a ``<Msg>Counter`` (incremented per frame of that
    message, wrapping at its width: 0..15 for 4 bits) and a ``<Msg>CRC`` in
    byte 7 computed over bytes 0..6 (:func:`~online_id.io.crc.crc8_j1850`).
    Values are clamped to the signal ranges; NaN/inf become 0 (and clear ``Valid``).
    """

    def __init__(self, db: Any = None, names: Mapping[str, str] | None = None, *, source: str = "the DBC") -> None:
        db = db if db is not None else load_dbc()
        self.names = {**OUTPUT_MESSAGES, **dict(names or {})}
        unknown = set(self.names) - set(OUTPUT_MESSAGES)
        if unknown:
            raise ConfigError(f"Expected output keys among {', '.join(OUTPUT_MESSAGES)}, but got {sorted(unknown)}.")
        self._specs: dict[str, _OutSpec] = {}
        self._by_id: dict[int, _OutSpec] = {}
        self._count: dict[str, int] = {}
        for key, name in self.names.items():
            if key in OPTIONAL_OUTPUTS and name not in {m.name for m in db.messages}:
                continue
            msg = _message(db, name, source, f"{key} output")
            counter = _signal(msg, f"{name}Counter", source, "alive counter")
            crc = _signal(msg, f"{name}CRC", source, "CRC-8 over bytes 0..6")
            crc_start = 56 if crc.byte_order == "little_endian" else 63
            if msg.length != 8 or crc.length != 8 or crc.start != crc_start:
                raise DbcError(f'{source}: expected message "{name}" of 8 bytes with signal "{crc.name}" '
                               f"filling byte 7, but got length {msg.length}, signal start {crc.start} "
                               f"length {crc.length}.")
            bounds = {s.name: _encodable_range(s) for s in msg.signals}
            spec = _OutSpec(msg, counter.name, crc.name, 1 << counter.length, bounds,
                            _packer(msg, counter.name, crc.name, bounds), int(msg.frame_id))
            self._specs[key] = spec
            self._by_id[int(msg.frame_id)] = spec
            self._count[key] = 0
        self._ready: tuple | None = None  # (values, alive counter, frame) of an OidEstimate encoded ahead
        self.command_answer: dict[str, int] = {}
        """The status frame's answer to the last command frame (signals LastCommand, CommandResult,
        CommandCounterEcho; a DBC without them leaves them out), set by :meth:`answer_command`."""

    def answer_command(self, command: int, result: int, counter: int | None) -> None:
        """Carry the answer to a command frame on the status frames from now on (see the DBC's comments)."""
        self.command_answer = {"LastCommand": command, "CommandResult": result,
                               "CommandCounterEcho": (counter or 0) % 64}

    def encode(self, pub: Publication, skip_first: bool = False) -> list[tuple[int, bytes]]:
        """Frames ``(arbitration_id, data)`` of one publication (EstimateOut gives two); ``skip_first``: all but
        the first, which :meth:`encode_first` gave (each message counts its own frames, so the frames are the
        same either way)."""
        if isinstance(pub, EstimateOut):
            return [self._shaft(pub)] if skip_first else [self._estimate(pub), self._shaft(pub)]
        first = None if skip_first else self.encode_first(pub)
        return [] if first is None else [first]

    def _estimate(self, pub: EstimateOut) -> tuple[int, bytes]:
        values = _estimate_values(pub)
        ready, self._ready = self._ready, None
        count = self._count["estimate"]
        if ready is not None and ready[1] == count and ready[0] == _same(values):
            self._count["estimate"] = (count + 1) % self._specs["estimate"].wrap
            return ready[2]
        return self._encode("estimate", values)

    def prepare_estimate(self, pub: EstimateOut) -> None:
        """Encode the OidEstimate of ``pub`` now, as the next frame of that message, without counting it.

        The live loop calls this on the sample before a publication, with the estimate the pipeline made
        ahead for it (:attr:`~online_id.service.pipeline.Pipeline.estimate_ahead`): the publication's
        OidEstimate is then this frame when its values and the alive counter are still the same (else it is
        encoded afresh), so the frame the bus is owed at once is ready.  The bytes are the same either way.
        """
        values = _estimate_values(pub)
        count = self._count["estimate"]
        try:
            self._ready = (_same(values), count, self._pack("estimate", values, count))
        except DbcError:
            self._ready = None  # the publication encodes it, and reports what is wrong

    def _shaft(self, pub: EstimateOut) -> tuple[int, bytes]:
        ok = bool(pub.valid) and math.isfinite(pub.c_s) and math.isfinite(pub.d_s)
        return self._encode("shaft", {"ShaftStiffness": pub.c_s, "ShaftDamping": pub.d_s, "Valid": ok})

    def rehearse(self) -> None:
        """Pack an OidEstimate without sending or counting it (nothing changes): the live loop calls this on the
        frames just before a publication, so that the encoding's code and data are in the processor's caches
        when the publication's frame is owed to the bus."""
        spec = self._specs["estimate"]
        if spec.packer is not None:
            word = spec.packer.pack(_REHEARSAL, 0)
            if word is not None:
                crc8_j1850(word.to_bytes(8, "little")[:7])

    def encode_first(self, pub: Publication) -> tuple[int, bytes] | None:
        """The first frame of one publication (of an EstimateOut, its OidEstimate); None for an output the DBC
        lacks (:data:`OPTIONAL_OUTPUTS`), which is never sent."""
        if isinstance(pub, EstimateOut):
            return self._estimate(pub)
        if isinstance(pub, QualityOut):
            fpe = float(pub.fpe)
            return self._encode("quality", {
                "ResidualRms": pub.residual_rms,
                "Fpe": math.sqrt(fpe) if fpe >= 0.0 else math.nan,
                "Excitation": pub.excitation,
                "SamplesUsed": pub.samples_used,
            })
        if isinstance(pub, StatusOut):
            return self._encode("status", {"State": int(pub.state), "BadFrames": pub.bad_frames,
                                           "MissingFrames": pub.missing_frames, **self.command_answer})
        if isinstance(pub, AlertOut):
            return self._encode("alert", {"AlertKind": int(pub.kind), "Severity": pub.severity,
                                          "DriftPct": pub.value_pct, "SpeedRpm": pub.speed_rpm})
        if isinstance(pub, ExcitationOut):
            return self._encode("excitation", {"TorqueOffset": pub.torque_offset_nm, "Active": bool(pub.active)})
        if isinstance(pub, FreshnessOut):
            if "freshness" not in self._specs:
                return None
            return self._encode("freshness", {"FreshnessValue": pub.freshness, "Authenticated": pub.authenticated})
        raise TypeError(f"Expected EstimateOut, QualityOut, StatusOut, AlertOut, ExcitationOut or FreshnessOut, "
                        f"but got {type(pub).__name__}.")

    def _encode(self, key: str, values: Mapping[str, float]) -> tuple[int, bytes]:
        count = self._count[key]
        self._count[key] = (count + 1) % self._specs[key].wrap
        return self._pack(key, values, count)

    def _pack(self, key: str, values: Mapping[str, float], count: int) -> tuple[int, bytes]:
        """The frame of output ``key`` with ``values`` and alive counter ``count`` (nothing counted)."""
        spec = self._specs[key]
        word = spec.packer.pack(values, count) if spec.packer is not None else None
        if word is not None:
            data = bytearray(word.to_bytes(8, "little"))
        else:
            phys: dict[str, float] = {}
            for name, (lo, hi) in spec.bounds.items():
                v = float(values.get(name, 0.0))
                if not math.isfinite(v):
                    v = 0.0
                phys[name] = min(max(v, lo), hi)
            phys[spec.counter] = count
            phys[spec.crc] = 0
            try:
                # not strict: every value is clamped to what its signal can carry (``_encodable_range``) and every
                # signal is given, which is what cantools' strict check verifies, at 40 % of the encoding's cost
                data = bytearray(spec.message.encode(phys, scaling=True, padding=False, strict=False))
            except (cantools.database.Error, ValueError, KeyError) as err:
                raise DbcError(f'Cannot encode message "{spec.message.name}" from {dict(values)}: {err}') from err
        data[7] = crc8_j1850(data[:7])
        return spec.frame_id, bytes(data)

    def verify(self, arbitration_id: int, data: bytes | bytearray) -> bool:
        """True when ``data`` is an 8-byte output frame of this DBC with a correct CRC."""
        return (arbitration_id in self._by_id and data is not None and len(data) == 8
                and crc8_j1850(bytes(data[:7])) == data[7])

    def output_ids(self, frame_ids: Mapping[str, int] | None = None) -> dict[int, str]:
        """Arbitration ID -> message name of every output (``frame_ids``: the config's ``publish.frame_ids``)."""
        remap = dict(frame_ids or {})
        return {int(remap.get(spec.message.name, fid)): spec.message.name for fid, spec in self._by_id.items()}

    def decode_named(self, name: str, data: bytes | bytearray) -> tuple[dict[str, float | str], int]:
        """Values of output message ``name`` (choices as their names, e.g. ``State: TRACKING``) and its
        alive counter; the CRC signal is left out.  DbcError when the length or the CRC is wrong."""
        spec = next(sp for sp in self._specs.values() if sp.message.name == name)
        if data is None or len(data) != 8 or crc8_j1850(bytes(data[:7])) != data[7]:
            raise DbcError(f'Expected message "{name}" with a valid CRC-8 in byte 7, but got data '
                           f"{bytes(data or b'').hex().upper()}.")
        raw = spec.message.decode(bytes(data), decode_choices=True)
        values = {k: (str(v) if not isinstance(v, int | float) else v) for k, v in raw.items() if k != spec.crc}
        return values, int(values.pop(spec.counter))

    def decode(self, arbitration_id: int, data: bytes | bytearray) -> dict[str, float]:
        """Physical values of an output frame (for consumers and tests); DbcError if it does not verify."""
        if not self.verify(arbitration_id, data):
            raise DbcError(f"Expected an output frame with a valid CRC, but got id 0x{arbitration_id:X} "
                           f"data {bytes(data or b'').hex()}.")
        return dict(self._by_id[arbitration_id].message.decode(bytes(data), decode_choices=False))
