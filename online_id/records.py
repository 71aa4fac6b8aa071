"""Record types shared by the core, the adapters and the CLI.

Everything here is in SI units: seconds, rad/s, Nm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class BenchData:
    """Bench signals on one uniform time grid, in SI units.

    Attributes
    ----------
    time_s
        Sample times [s], strictly increasing.
    dyno_speed_rad_s, engine_speed_rad_s
        Shaft speeds [rad/s].
    dyno_torque_nm
        Dyno (load) torque [Nm], positive = braking the shaft.
    source
        Where the data came from (a file name), used in error messages.
    """

    time_s: np.ndarray
    dyno_speed_rad_s: np.ndarray
    engine_speed_rad_s: np.ndarray
    dyno_torque_nm: np.ndarray
    source: str = "<memory>"
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def engine_speed_rpm(self) -> np.ndarray:
        return self.engine_speed_rad_s * (30.0 / np.pi)

    @property
    def dyno_speed_rpm(self) -> np.ndarray:
        return self.dyno_speed_rad_s * (30.0 / np.pi)

    def slice(self, start: int, stop: int) -> "BenchData":
        """Samples ``start:stop`` as a new record."""
        return BenchData(
            self.time_s[start:stop],
            self.dyno_speed_rad_s[start:stop],
            self.engine_speed_rad_s[start:stop],
            self.dyno_torque_nm[start:stop],
            self.source,
            dict(self.meta),
        )


# --- streaming records: what the CAN adapters and the pipeline exchange -------------

from enum import IntEnum  # noqa: E402

ROLES = ("dyno_speed", "engine_speed", "dyno_torque")
"""The three input roles. Speeds are in rad/s, torque in Nm (positive = braking)."""


class ServiceState(IntEnum):
    """Health state published in the status frame."""

    STARTING = 0
    LEARNING = 1
    TRACKING = 2
    NO_EXCITATION = 3
    INPUT_TIMEOUT = 4
    FAULT = 5


class AlertKind(IntEnum):
    """Kinds of alert published in the alert frame."""

    NONE = 0
    FREQ_DRIFT = 1
    DAMPING_DRIFT = 2
    ESTIMATOR_RESET = 3
    INPUT_FAULT = 4


class FrameFault(IntEnum):
    """Why an input frame was not used (each kind is counted and reported)."""

    UNKNOWN_ID = 0  # not an input frame (foreign traffic is normal on a bench bus)
    BAD_DLC = 1  # payload length does not match the DBC
    MALFORMED = 2  # cannot be decoded
    OUT_OF_RANGE = 3  # physical value outside the signal's range in the DBC
    NOT_FINITE = 4  # NaN or infinite physical value
    COUNTER_JUMP = 5  # alive counter skipped values (frames lost)
    DUPLICATE = 6  # same alive counter twice (frame repeated)
    TIME_BACKWARDS = 7  # timestamp older than the last sample of that role
    BAD_TIME = 8  # timestamp NaN, infinite, or far ahead of the stream clock and not confirmed
    BAD_CRC = 9  # input CRC (where the mapping has one) does not match the payload
    COMMAND_REFUSED = 10  # command frame with a bad CRC, a freshness value that is not new, or a wrong MAC


@dataclass(frozen=True)
class SignalSample:
    """One decoded input value: ``role`` (see :data:`ROLES`) in SI units at ``t_s``."""

    role: str
    value: float
    t_s: float
    counter: int | None = None


@dataclass(frozen=True)
class EstimateOut:
    """Driveline estimate to publish."""

    t_s: float
    f0_hz: float
    zeta: float
    c_s: float
    d_s: float
    valid: bool


@dataclass(frozen=True)
class QualityOut:
    """Model quality to publish."""

    t_s: float
    residual_rms: float
    fpe: float
    excitation: float
    samples_used: int


@dataclass(frozen=True)
class StatusOut:
    """Health and input counters to publish."""

    t_s: float
    state: ServiceState
    bad_frames: int
    missing_frames: int


@dataclass(frozen=True)
class AlertOut:
    """An alert: what changed, by how much, where (``message`` is for logs, not CAN)."""

    t_s: float
    kind: AlertKind
    severity: int  # 1 warning, 2 fault
    value_pct: float
    speed_rpm: float
    message: str


@dataclass(frozen=True)
class ExcitationOut:
    """PRBS torque-offset request to the bench (paper's discrete binary test signal)."""

    t_s: float
    torque_offset_nm: float
    active: bool


@dataclass(frozen=True)
class FreshnessOut:
    """The command freshness value: the last one accepted (the next command carries this + 1 .. + 64), and
    whether commands must carry a MAC (see :mod:`online_id.service.commands`)."""

    t_s: float
    freshness: int
    authenticated: bool


Publication = EstimateOut | QualityOut | StatusOut | AlertOut | ExcitationOut | FreshnessOut


DEMAND_COLUMN = "torque_demand_nm"
"""The bench CSV column of the recorded test-torque demand [Nm] (``simulate --with-demand`` writes it)."""
