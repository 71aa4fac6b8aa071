"""What a command frame from the bus may do: freshness, authentication and policy, between decoder and pipeline.

The decoder (:mod:`online_id.io.dbc`) has already refused command frames
with a wrong CRC or an undefined value, and read the frame's freshness bits
and MAC.  Here, as AUTOSAR SecOC does it (see the DBC and ``docs/security.md``):

* **Freshness.** The gate keeps ``freshness``, the last freshness value it
  accepted (32 bits). A command carries the low bits of its own value F;
  F is rebuilt as the one value above ``freshness`` with those bits, and the
  command is refused unless ``F <= freshness + FRESHNESS_WINDOW``. An
  accepted command (a first RELEARN awaiting its confirmation too) moves
  ``freshness`` to F, and it never goes back: a frame captured and sent
  again is refused at any later time. The value is kept on disk at once
  (:meth:`CommandGate.keep_in`, before the command acts; a command whose
  value cannot be kept is refused) and, at the first command frame after a
  start, raised to the clock's Unix seconds (the frame's timestamp) if it is
  below: a service without a state directory, or with its file lost, starts
  above every value it can have accepted before (it accepts fewer than one
  command a second).
* **Authentication** (``commands.key_file``): the frame's MAC must be the
  truncated HMAC-SHA256 of its ID, command and F (:mod:`online_id.io.auth`);
  a wrong MAC is refused and counted, and after :data:`MAC_FAILURES_MAX`
  wrong MACs within :data:`MAC_FAILURE_WINDOW_S` every command is refused
  until they age out, so that the 32-bit MAC cannot be found by trying.
  Without a key (plain mode) any node on the bus can send a command with a
  new freshness value: the service says so at start.
* **Requests.** ``NONE`` (0) asks for the freshness value: the runtime answers
  with an ``OidFreshness`` frame; it acts on nothing and needs no MAC.
* **Policy.** ``ACK_ALERT`` and ``RESET_ESTIMATOR`` act on one frame;
  ``RELEARN_BASELINE`` forgets every learned baseline, so by default
  (``commands.relearn: confirm``) it acts only when a second RELEARN frame
  follows the first within ``commands.confirm_s`` (``online-id relearn``
  sends both); ``allow`` acts on one frame; ``disabled`` never acts on a
  frame from the bus.

Every command frame but a request gives one log line naming the frame (ID
and data) and what was done; the service writes them to its log (the
journal under systemd).  :attr:`CommandGate.refusals` counts the refused
frames by reason; those refused for what they are (not for the policy) are
bad frames too (``COMMAND_REFUSED`` in the pipeline's counters).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable

from pathlib import Path

from online_id.config import CommandSettings
from online_id.errors import InputDataError
from online_id.io.auth import ALGORITHM, mac_matches
from online_id.io.dbc import BenchCommand, CommandSample
from online_id.io.statefile import load_state, save_state

MAX_LOG = 100
FRESHNESS_BITS = 32
FRESHNESS_WINDOW = 64
"""A command's freshness value is accepted from the last accepted one + 1 to this much above it."""
MAC_FAILURES_MAX = 16
MAC_FAILURE_WINDOW_S = 60.0
FRESHNESS_FILE = "online-id-command-freshness.json"
"""Beside the state file: the last accepted freshness value, written (fsync) before a command acts."""


def frame_text(arbitration_id: int, data: bytes | bytearray | None) -> str:
    """A frame as candump writes it: ``120#0205000000000078``."""
    return f"{arbitration_id:03X}#{bytes(data or b'').hex().upper()}"


def _is_time(t_s: float) -> bool:
    """A timestamp the freshness can start from: Unix seconds (or a stream's) within 32 bits."""
    return math.isfinite(t_s) and 0 <= t_s < 2 ** FRESHNESS_BITS - 2 ** 16


class CommandGate:
    """Admit command frames to the pipeline by freshness, MAC and policy (see module notes).

    Parameters
    ----------
    settings
        ``commands`` of the config.
    key
        The HMAC key of authenticated mode (:func:`online_id.io.auth.read_key`); None: plain mode.
    freshness_bits
        Width of the frame's freshness signal (the low bits of the 32-bit value); 0: the frame has none,
        then no command is accepted.
    """

    def __init__(self, settings: CommandSettings | None = None, key: bytes | None = None,
                 freshness_bits: int = 16) -> None:
        self.settings = settings or CommandSettings()
        self.key = key
        self.freshness_bits = int(freshness_bits)
        self.freshness: int | None = None  # the last accepted value; None until the first command frame
        self._kept: int | None = None  # the value read from disk (keep_in), until the first command frame
        self._store: Callable[[int], None] | None = None
        self._pending: tuple[float, int] | None = None  # a first RELEARN frame: time and freshness value
        self._mac_failures: deque[float] = deque()
        self._log: deque[str] = deque(maxlen=MAX_LOG)
        self.accepted = 0
        self.refused = 0
        self.awaiting = 0
        self.refusals: Counter[str] = Counter()
        self.faulty = False  # the last frame refused was a bad frame (not fresh, wrong MAC ...), not policy

    @property
    def authenticated(self) -> bool:
        return self.key is not None

    def mode_text(self) -> str:
        """One line for the log at start: authenticated or not, and where the freshness is kept."""
        kept = "kept in the state directory" if self._store is not None else \
            "kept in memory only (no state directory): above the clock's Unix seconds at each start"
        if self.authenticated:
            return (f"commands are authenticated ({ALGORITHM}, truncated MAC over ID, command and freshness); "
                    f"freshness {kept}")
        return (f"commands are NOT authenticated (no commands.key_file): any node on the bus can send one; "
                f"a replayed frame fails its freshness check, {kept}")

    def keep_in(self, store: Callable[[int], None], kept: int | None) -> None:
        """Keep every accepted freshness value with ``store`` (before the command acts); ``kept``: the value
        kept before (read at start), or None."""
        self._store = store
        self._kept = kept

    def _say(self, cmd: str, frame: str, what: str) -> None:
        self._log.append(f"command {cmd} from frame {frame}: {what}")

    def current(self, t_s: float) -> int:
        """The last accepted freshness value; at the first call, the one kept or the clock's seconds."""
        if self.freshness is not None:
            return self.freshness
        if not _is_time(t_s):  # no clock to start from
            return self._kept or 0
        self.freshness = max(self._kept or 0, int(t_s))
        return self.freshness

    def admit(self, sample: CommandSample, arbitration_id: int, data: bytes | bytearray | None) -> bool:
        """True when the pipeline shall act on ``sample`` (logged either way; a request is not)."""
        last = self.current(sample.t_s)
        if sample.command == BenchCommand.NONE:
            return False
        frame = frame_text(arbitration_id, data)
        name = sample.command.name
        if not _is_time(sample.t_s):
            return self._refuse("bad time", name, frame, f"its timestamp {sample.t_s!r} is no time")
        if sample.freshness is None or not self.freshness_bits:
            return self._refuse("no freshness", name, frame, "the frame has no freshness value (mapping."
                                                           "command_freshness)")
        wrap = 1 << self.freshness_bits
        value = last + ((sample.freshness - last - 1) % wrap) + 1  # the one value above `last` with these bits
        if value - last > FRESHNESS_WINDOW or value >= 2 ** FRESHNESS_BITS:
            return self._refuse("not fresh", f"{name} (freshness bits {sample.freshness})", frame,
                                f"its freshness is not new: the last accepted is {last}, a command needs "
                                f"{last + 1} to {last + FRESHNESS_WINDOW} (a replayed or forged frame, or a sender "
                                f"that did not ask for the freshness value)")
        name = f"{name} (freshness {value})"
        if self.authenticated:
            t = sample.t_s
            while self._mac_failures and not 0 <= t - self._mac_failures[0] < MAC_FAILURE_WINDOW_S:
                self._mac_failures.popleft()
            if len(self._mac_failures) >= MAC_FAILURES_MAX:
                return self._refuse("locked", name, frame, f"{len(self._mac_failures)} wrong MACs within "
                                    f"{MAC_FAILURE_WINDOW_S:g} s: every command is refused until they age out")
            if sample.mac is None or not mac_matches(self.key, arbitration_id, int(sample.command), value,
                                                     sample.mac):
                self._mac_failures.append(t)
                return self._refuse("wrong MAC", name, frame, f"its MAC does not match ({ALGORITHM} with the key "
                                                              f"of commands.key_file)")
        if self._store is not None:
            try:
                self._store(value)
            except OSError as err:
                return self._refuse("not kept", name, frame, f"its freshness value cannot be kept on disk "
                                                             f"({err}): refused, so that it cannot be replayed")
        self.freshness = value
        if sample.command != BenchCommand.RELEARN_BASELINE or self.settings.relearn == "allow":
            return self._accept(name, frame, "accepted")
        if self.settings.relearn == "disabled":
            return self._refuse("policy", name, frame, "remote relearn is disabled (config commands.relearn)")
        pending, self._pending = self._pending, None
        if pending is not None and 0.0 <= sample.t_s - pending[0] <= self.settings.confirm_s:
            return self._accept(name, frame, f"confirmed {sample.t_s - pending[0]:.3f} s after the first: accepted")
        self._pending = (sample.t_s, value)
        self.awaiting += 1
        self._say(name, frame, f"awaiting confirmation: a second RELEARN frame within "
                               f"{self.settings.confirm_s:g} s (config commands.relearn)")
        return False

    def _accept(self, name: str, frame: str, what: str) -> bool:
        self.accepted += 1
        self._say(name, frame, what)
        return True

    def _refuse(self, reason: str, name: str, frame: str, why: str) -> bool:
        self.refused += 1
        self.faulty = reason != "policy"
        self.refusals[reason] += 1
        self._say(name, frame, f"refused: {why}")
        return False

    def refuse(self, arbitration_id: int, data: bytes | bytearray | None, why: str) -> None:
        """A command frame the decoder refused (bad CRC, ...): logged and counted."""
        self.refused += 1
        self.refusals["bad frame"] += 1
        self._log.append(f"command frame {frame_text(arbitration_id, data)} refused: {why}")

    def take_log(self) -> list[str]:
        """The log lines since the last call."""
        out = list(self._log)
        self._log.clear()
        return out


def keep_freshness(gate: CommandGate, path: Path, say: Callable[[str], None]) -> None:
    """Keep ``gate``'s freshness in ``path`` (JSON, written atomically with fsync), starting from the value
    kept there; a file that cannot be read is said and the gate starts from the clock (see module notes)."""
    kept = None
    try:
        doc = load_state(path)
        if doc is not None:
            kept = doc.get("command_freshness")
            if not isinstance(kept, int) or isinstance(kept, bool) or not 0 <= kept < 2 ** FRESHNESS_BITS:
                say(f"{path}: command_freshness is not a 32-bit count ({kept!r}): starting from the clock")
                kept = None
    except (InputDataError, AttributeError) as err:
        say(f"{path}: cannot read the command freshness ({err}): starting from the clock")
    gate.keep_in(lambda value: save_state(path, {"command_freshness": int(value)}), kept)
