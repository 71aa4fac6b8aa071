"""Frames in -> frames out: the DBC codec around the pipeline.

Shared by the live service, the replay of logs and the demo, so that all
three run exactly the same code from the first byte of a frame to the last
byte of a published frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from online_id.service.commands import CommandGate
from online_id.config import MappingSettings, RoleSettings, Settings
from online_id.errors import ConfigError
from online_id.io.auth import read_key
from online_id.io.dbc import CommandSample, CommandSignal, InputDecoder, RoleMapping, RoleSignal, load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.service.pipeline import Pipeline
from online_id.records import EstimateOut, FrameFault, FreshnessOut, Publication

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
        self._rest: list = []  # the values of a frame after the one whose publication publications() split
        self._prepared: Any = None  # the estimate made ahead whose OidEstimate the encoder holds (publications())
        self.on_publish: Any = None  # also hand every list of publications here (the service's telemetry)

    def frames(self, pubs: list[Publication], skip_first: bool = False) -> list[OutFrame]:
        """The frames of ``pubs`` (``skip_first``: without the first frame of ``pubs[0]``, which
        :meth:`first_frame` gave)."""
        out: list[OutFrame] = []
        if self.on_publish is not None:
            self.on_publish(pubs)
        for k, pub in enumerate(pubs):
            for ident, data in self.encoder.encode(pub, skip_first=skip_first and k == 0):
                out.append((self._remap.get(ident, ident), data))
        self.frames_out += len(out)
        return out

    def first_frame(self, pub: Publication) -> OutFrame | None:
        """The first frame of ``pub`` alone (of an :class:`EstimateOut`, its OidEstimate; None for an output the
        DBC lacks); ``frames(pubs, skip_first=True)`` gives the rest."""
        frame = self.encoder.encode_first(pub)
        if frame is None:
            return None
        self.frames_out += 1
        return self._remap.get(frame[0], frame[0]), frame[1]

    def on_frame(self, t_s: float, arbitration_id: int, data: bytes, is_extended: bool = False,
                 is_error: bool = False) -> list[OutFrame]:
        """One received frame; returns the frames to publish."""
        pubs = self.all_publications(t_s, arbitration_id, data, is_extended, is_error)
        return self.frames(pubs) if pubs else []

    def all_publications(self, t_s: float, arbitration_id: int, data: bytes, is_extended: bool = False,
                         is_error: bool = False) -> list[Publication]:
        """One received frame; returns everything it publishes, not yet encoded: :meth:`publications` and
        :meth:`finish` in one (what replay and the evaluation's frame path take)."""
        return self.publications(t_s, arbitration_id, data, is_extended, is_error) + self.finish()

    def publications(self, t_s: float, arbitration_id: int, data: bytes, is_extended: bool = False,
                     is_error: bool = False) -> list[Publication]:
        """One received frame; returns what it publishes, not yet encoded (:meth:`frames` encodes them), up to
        and including the estimate of its first publication: :meth:`finish`, which must follow, gives the rest.

        The live service encodes and sends that estimate's frame (:meth:`first_frame`) before the rest of
        the publication is made, and before the samples after it in the frame are taken (see
        :meth:`Pipeline.on_signal` with ``split``); replay and the tests take :meth:`on_frame` or
        :meth:`all_publications`.
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
        pipeline = self.pipeline
        for k, sample in enumerate(res):
            pubs.extend(pipeline.on_signal(sample, split=True))
            if pipeline.split_pending:
                self._rest = res[k + 1:]
                break
        ahead = pipeline.estimate_ahead
        if ahead is not None:
            if ahead is not self._prepared:  # the next sample publishes this estimate: its OidEstimate now
                self._prepared = ahead
                self.encoder.prepare_estimate(EstimateOut(math.nan, ahead.f0_hz, ahead.zeta, math.nan, math.nan,
                                                          ahead.valid))
        elif not pubs and pipeline.publishes_next:
            self.encoder.rehearse()  # the next sample publishes: its OidEstimate's encoding into the caches now
        return pubs

    def finish(self) -> list[Publication]:
        """The rest of what the last :meth:`publications` left (nothing if it made no publication)."""
        pipeline = self.pipeline
        if not pipeline.split_pending:
            return []
        pubs = pipeline.finish()
        rest, self._rest = self._rest, []
        for sample in rest:
            pubs.extend(pipeline.on_signal(sample))
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
