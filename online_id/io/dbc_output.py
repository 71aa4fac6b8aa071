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
from online_id.io.dbc import _message, _signal, load_dbc
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


@dataclass(frozen=True)
class _OutSpec:
    message: Any
    counter: str
    crc: str
    wrap: int
    bounds: dict[str, tuple[float, float]]


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
            spec = _OutSpec(msg, counter.name, crc.name, 1 << counter.length,
                            {s.name: _encodable_range(s) for s in msg.signals})
            self._specs[key] = spec
            self._by_id[int(msg.frame_id)] = spec
            self._count[key] = 0
        self.command_answer: dict[str, int] = {}
        """The status frame's answer to the last command frame (signals LastCommand, CommandResult,
        CommandCounterEcho; a DBC without them leaves them out), set by :meth:`answer_command`."""

    def answer_command(self, command: int, result: int, counter: int | None) -> None:
        """Carry the answer to a command frame on the status frames from now on (see the DBC's comments)."""
        self.command_answer = {"LastCommand": command, "CommandResult": result,
                               "CommandCounterEcho": (counter or 0) % 64}

    def encode(self, pub: Publication) -> list[tuple[int, bytes]]:
        """Frames ``(arbitration_id, data)`` of one publication (EstimateOut gives two)."""
        if isinstance(pub, EstimateOut):
            ok = bool(pub.valid) and all(math.isfinite(v) for v in (pub.f0_hz, pub.zeta))
            ok_shaft = bool(pub.valid) and all(math.isfinite(v) for v in (pub.c_s, pub.d_s))
            return [
                self._encode("estimate", {"ResonanceFreq": pub.f0_hz, "DampingRatio": pub.zeta, "Valid": ok}),
                self._encode("shaft", {"ShaftStiffness": pub.c_s, "ShaftDamping": pub.d_s, "Valid": ok_shaft}),
            ]
        if isinstance(pub, QualityOut):
            fpe = float(pub.fpe)
            return [self._encode("quality", {
                "ResidualRms": pub.residual_rms,
                "Fpe": math.sqrt(fpe) if fpe >= 0.0 else math.nan,
                "Excitation": pub.excitation,
                "SamplesUsed": pub.samples_used,
            })]
        if isinstance(pub, StatusOut):
            return [self._encode("status", {"State": int(pub.state), "BadFrames": pub.bad_frames,
                                            "MissingFrames": pub.missing_frames, **self.command_answer})]
        if isinstance(pub, AlertOut):
            return [self._encode("alert", {"AlertKind": int(pub.kind), "Severity": pub.severity,
                                           "DriftPct": pub.value_pct, "SpeedRpm": pub.speed_rpm})]
        if isinstance(pub, ExcitationOut):
            return [self._encode("excitation", {"TorqueOffset": pub.torque_offset_nm, "Active": bool(pub.active)})]
        if isinstance(pub, FreshnessOut):
            if "freshness" not in self._specs:
                return []
            return [self._encode("freshness", {"FreshnessValue": pub.freshness, "Authenticated": pub.authenticated})]
        raise TypeError(f"Expected EstimateOut, QualityOut, StatusOut, AlertOut, ExcitationOut or FreshnessOut, "
                        f"but got {type(pub).__name__}.")

    def _encode(self, key: str, values: Mapping[str, float]) -> tuple[int, bytes]:
        spec = self._specs[key]
        phys: dict[str, float] = {}
        for name, (lo, hi) in spec.bounds.items():
            v = float(values.get(name, 0.0))
            if not math.isfinite(v):
                v = 0.0
            phys[name] = min(max(v, lo), hi)
        phys[spec.counter] = self._count[key]
        self._count[key] = (self._count[key] + 1) % spec.wrap
        phys[spec.crc] = 0
        try:
            # not strict: every value is clamped to what its signal can carry (``_encodable_range``) and every
            # signal is given, which is what cantools' strict check verifies, at 40 % of the encoding's cost
            data = bytearray(spec.message.encode(phys, scaling=True, padding=False, strict=False))
        except (cantools.database.Error, ValueError, KeyError) as err:
            raise DbcError(f'Cannot encode message "{spec.message.name}" from {dict(values)}: {err}') from err
        data[7] = crc8_j1850(data[:7])
        return int(spec.message.frame_id), bytes(data)

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
