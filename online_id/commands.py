"""What a command frame from the bus may do: the policy between the decoder and the pipeline.

The decoder (:mod:`online_id.io.dbc`) has already refused command frames
with a wrong CRC, a repeated or stale alive counter, or an undefined value.
What is left is policy:

* ``ACK_ALERT`` and ``RESET_ESTIMATOR`` act on one frame (an acknowledged
  alarm is raised again if the deviation persists; a reset estimator learns
  again, baselines kept);
* ``RELEARN_BASELINE`` forgets every learned baseline, so by default
  (``commands.relearn: confirm``) it acts only when a second RELEARN frame,
  with another counter, follows the first within ``commands.confirm_s``
  (``online-id relearn`` sends both).  ``allow`` acts on one frame;
  ``disabled`` never acts on a frame from the bus.

Every command frame, refused ones included, gives one log line naming the
frame (ID and data) and what was done; the service writes them to its log
(the journal under systemd).
"""

from __future__ import annotations

from collections import deque

from online_id.config import CommandSettings
from online_id.io.dbc import BenchCommand, CommandSample

MAX_LOG = 100


def frame_text(arbitration_id: int, data: bytes | bytearray | None) -> str:
    """A frame as candump writes it: ``120#0205000000000078``."""
    return f"{arbitration_id:03X}#{bytes(data or b'').hex().upper()}"


class CommandGate:
    """Admit command frames to the pipeline by the policy of the module notes."""

    def __init__(self, settings: CommandSettings | None = None) -> None:
        self.settings = settings or CommandSettings()
        self._pending: tuple[float, int | None] | None = None  # a first RELEARN frame: time and counter
        self._log: deque[str] = deque(maxlen=MAX_LOG)
        self.accepted = 0
        self.refused = 0
        self.awaiting = 0

    def _say(self, cmd: str, frame: str, what: str) -> None:
        self._log.append(f"command {cmd} from frame {frame}: {what}")

    def admit(self, sample: CommandSample, arbitration_id: int, data: bytes | bytearray | None) -> bool:
        """True when the pipeline shall act on ``sample`` (logged either way)."""
        frame = frame_text(arbitration_id, data)
        name = f"{sample.command.name} (counter {sample.counter})"
        if sample.command == BenchCommand.NONE:
            return False
        if sample.command != BenchCommand.RELEARN_BASELINE or self.settings.relearn == "allow":
            return self._accept(name, frame, "accepted")
        if self.settings.relearn == "disabled":
            self.refused += 1
            self._say(name, frame, "refused: remote relearn is disabled (config commands.relearn)")
            return False
        pending, self._pending = self._pending, None
        if pending is not None and pending[1] != sample.counter \
                and 0.0 <= sample.t_s - pending[0] <= self.settings.confirm_s:
            return self._accept(name, frame, f"confirmed {sample.t_s - pending[0]:.3f} s after the first: accepted")
        self._pending = (sample.t_s, sample.counter)
        self.awaiting += 1
        self._say(name, frame, f"awaiting confirmation: a second RELEARN frame within "
                               f"{self.settings.confirm_s:g} s (config commands.relearn)")
        return False

    def _accept(self, name: str, frame: str, what: str) -> bool:
        self.accepted += 1
        self._say(name, frame, what)
        return True

    def refuse(self, arbitration_id: int, data: bytes | bytearray | None, why: str) -> None:
        """A command frame the decoder refused (bad CRC, repeated counter, ...): logged and counted."""
        self.refused += 1
        self._log.append(f"command frame {frame_text(arbitration_id, data)} refused: {why}")

    def take_log(self) -> list[str]:
        """The log lines since the last call."""
        out = list(self._log)
        self._log.clear()
        return out
