"""The pipeline's event log entry and the lanes of its worker (shared by the pipeline and its detection policy)."""

from __future__ import annotations

from dataclasses import dataclass, field

MAX_EVENTS = 10_000  # state changes kept for reports (bounded: a flapping bench must not grow memory)
WINDOW = "window"  # worker lane of the window refits and multi-start checks
PHYSICAL = "physical"  # worker lane of the physical-parameter fit
LINEARITY = "linearity"  # worker lane of the backlash test (see _test_backlash)


@dataclass
class Event:
    """A status change or alert kept for reports (times in stream seconds)."""

    t_s: float
    kind: str
    message: str = ""
    data: dict = field(default_factory=dict)
