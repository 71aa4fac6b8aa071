"""Frames in -> frames out: the DBC codec around the pipeline.

Shared by the live service, the replay of logs and the demo, so that all
three run exactly the same code from the first byte of a frame to the last
byte of a published frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from online_id.service.commands import CommandGate
from online_id.config import MappingSettings, RoleSettings, Settings
from online_id.errors import ConfigError
from online_id.io.auth import read_key
from online_id.io.dbc import CommandSample, CommandSignal, InputDecoder, RoleMapping, RoleSignal, load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.service.pipeline import Pipeline
from online_id.records import FrameFault, FreshnessOut, Publication

OutFrame = tuple[int, bytes]
ACCEPTED, AWAITING_CONFIRMATION, REFUSED = 1, 2, 3
"""Values of the status frame's CommandResult signal (see the DBC)."""


def _sign(role: str, rs: RoleSettings) -> int:
    if role == "dyno_torque":
        return {"braking": 1, "positive": 1, "driving": -1, "negative": -1}[rs.sign]
    return {"positive": 1, "braking": 1, "negative": -1, "driving": -1}[rs.sign]


def role_mapping(m: MappingSettings) -> RoleMapping:
    """The codec's role mapping from the configuration."""
    def rs(role: str) -> RoleSignal:
        r = getattr(m, role)
        return RoleSignal(r.message, r.signal, r.unit, _sign(role, r), r.counter, r.crc)

    return RoleMapping(rs("dyno_speed"), rs("engine_speed"), rs("dyno_torque"),
                       CommandSignal(m.command_message, m.command_signal, m.command_freshness, m.command_mac,
                                     m.command_crc))


def input_decoder(s: Settings, db: Any = None) -> InputDecoder:
    """The input side of the codec as the config maps it (``db``: the loaded ``s.dbc``, if at hand)."""
    return InputDecoder(db if db is not None else load_dbc(s.dbc), role_mapping(s.mapping),
                        source=s.dbc or "online_id.dbc")


@dataclass
class Runtime:
    """Decoder + pipeline + encoder (see module notes)."""

    settings: Settings
    worker: Any = None  # where slow work runs (see online_id.service.offload); None: inline
    pipeline: Pipeline = field(init=False)
    decoder: InputDecoder = field(init=False)
    encoder: OutputEncoder = field(init=False)

    def __post_init__(self) -> None:
        s = self.settings
        db = load_dbc(s.dbc)
        self.decoder = input_decoder(s, db)
        self.encoder = OutputEncoder(db, source=self.decoder.source)
        self.pipeline = Pipeline(s, worker=self.worker)
        key = None
        if s.commands.key_file is not None:
            if not self.decoder.command_mac_bytes:
                raise ConfigError("commands.key_file: authenticated commands need a MAC signal in the command "
                                  "message (mapping.command_mac)")
            key = read_key(s.commands.key_file)
        # what a command frame may do, its freshness and MAC (online_id.service.commands)
        self.commands = CommandGate(s.commands, key, self.decoder.command_freshness_bits)
        ids = {}
        for key, name in self.encoder.names.items():
            if name in s.publish.frame_ids:
                ids[int(db.get_message_by_name(name).frame_id)] = s.publish.frame_ids[name]
        self._remap = ids
        self.frames_in = 0
        self.frames_out = 0
        self.on_publish: Any = None  # also hand every list of publications here (the service's telemetry)

    def frames(self, pubs: list[Publication]) -> list[OutFrame]:
        out: list[OutFrame] = []
        if self.on_publish is not None:
            self.on_publish(pubs)
        for pub in pubs:
            for ident, data in self.encoder.encode(pub):
                out.append((self._remap.get(ident, ident), data))
        self.frames_out += len(out)
        return out

    def on_frame(self, t_s: float, arbitration_id: int, data: bytes, is_extended: bool = False,
                 is_error: bool = False) -> list[OutFrame]:
        """One received frame; returns the frames to publish."""
        pubs = self.publications(t_s, arbitration_id, data, is_extended, is_error)
        return self.frames(pubs) if pubs else []

    def publications(self, t_s: float, arbitration_id: int, data: bytes, is_extended: bool = False,
                     is_error: bool = False) -> list[Publication]:
        """One received frame; returns what it publishes, not yet encoded (:meth:`frames` encodes them).

        The live service encodes and sends a publication's first frame, its OidEstimate, before it encodes
        the others; replay and the tests take :meth:`on_frame`.
        """
        self.frames_in += 1
        if is_error:
            self.pipeline.on_fault(FrameFault.MALFORMED)
            return []
        res = self.decoder.decode(arbitration_id, data, t_s, is_extended)
        if isinstance(res, FrameFault):
            self.pipeline.on_fault(res)
            if res is FrameFault.COMMAND_REFUSED:
                self.commands.refuse(arbitration_id, data, self.decoder.last_fault)
                return self._answer(t_s, 0, REFUSED, None)
            return []
        if isinstance(res, CommandSample):
            awaiting = self.commands.awaiting
            if not self.commands.admit(res, arbitration_id, data):
                if int(res.command) == 0:  # a request for the freshness value
                    return [self._freshness(t_s)]
                if self.commands.awaiting > awaiting:
                    result = AWAITING_CONFIRMATION
                else:
                    result = REFUSED
                    if self.commands.faulty:  # stale, forged ...: a bad frame; the policy's refusals are not
                        self.pipeline.on_fault(FrameFault.COMMAND_REFUSED)
                return self._answer(t_s, int(res.command), result, res.freshness)
            done = self.pipeline.on_command(int(res.command), t_s)
            return done + self._answer(t_s, int(res.command), ACCEPTED, res.freshness)
        pubs: list[Publication] = []
        for sample in res:
            pubs.extend(self.pipeline.on_signal(sample))
        return pubs

    def _answer(self, t_s: float, command: int, result: int, freshness: int | None) -> list[Publication]:
        """A status frame at once, answering a command frame (signals LastCommand, CommandResult,
        CommandCounterEcho), and the freshness value a next command needs."""
        self.encoder.answer_command(command, result, freshness)
        return [self.pipeline.status(t_s), self._freshness(t_s)]

    def _freshness(self, t_s: float) -> FreshnessOut:
        return FreshnessOut(t_s, self.commands.current(t_s), self.commands.authenticated)

    @property
    def stream_clock(self) -> float:
        """The stream time of the newest input the pipeline took (NaN before one): what the service's loop
        ticks from; a frame judged bad (a time far ahead held or refused, a bad frame) never moves it."""
        return self.pipeline.assembler.now_s

    def tick_worker(self) -> list[OutFrame]:
        """No stream clock yet: only adopt finished slow work."""
        self.pipeline.poll_worker()
        return []

    def tick(self, now_s: float) -> list[OutFrame]:
        """The stream clock moved without a frame."""
        pubs = self.pipeline.tick(now_s)
        return self.frames(pubs) if pubs else []
