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
