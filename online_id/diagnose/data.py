"""The signals a diagnosis works on, validated where they are built.

A diagnosis needs one input ``u`` and one output ``y`` on a uniform grid.
Optional auxiliary signals let the residual tests look for more effects:

- ``shaft_speeds_rad_s``: speed of each rotating shaft; its integral is the
  shaft angle used for order spectra and rotation-order regressors;
- ``torsion``: relative motion across a compliant coupling (for the bench,
  the integral of dyno minus engine speed), for backlash;
- ``joints``: the twist across each joint of a rig whose both sides are
  measured (name ``a-b`` -> twist [rad of ``b``]), for backlash and Coulomb
  friction in that joint;
- ``torques``: a torque acting on a shaft (a load motor's), an input of that
  shaft's channel (:func:`online_id.diagnose.diagnosis.shaft_channels`);
- ``velocity``: the speed whose sign Coulomb friction follows (by default the
  output itself, which must then be a speed).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import cached_property
from dataclasses import dataclass, field

import numpy as np

from online_id.errors import InputDataError

MIN_SAMPLES = 100


@dataclass(frozen=True)
class DiagnoseData:
    """Input, output and auxiliary signals of one record, uniformly sampled.

    Attributes
    ----------
    u, y
        Input and output, equal length.
    fs_hz
        Sample rate.
    input_name, output_name
        Signal names used in reports (e.g. ``dyno_torque``, ``dyno_speed``).
    shaft_speeds_rad_s
        Shaft name -> speed [rad/s], for order analysis (may be empty).
    torsion
        Relative motion proxy (same length), or ``None``.
    joints
        Joint name -> twist across it (same length): backlash and Coulomb friction
        in that joint are candidates (may be empty).
    velocity
        Speed whose sign Coulomb friction follows; ``None`` means the output.
    output_is_velocity
        Whether the output itself is the velocity (then Coulomb friction is
        simulated from the simulated output).
    source
        Where the data came from, for error messages.
    shaft_rates
        Shaft name -> rate relative to the first shaft (gear ratios).  With two
        or more, rotation orders are searched on the grid the ratios imply and
        reported against the shaft they belong to
        (:mod:`online_id.diagnose.shafts`).
    notes
        How the record was put together (clock alignment, jitter), reported as is.
    """

    u: np.ndarray
    y: np.ndarray
    fs_hz: float
    input_name: str = "input"
    output_name: str = "output"
    shaft_speeds_rad_s: Mapping[str, np.ndarray] = field(default_factory=dict)
    torsion: np.ndarray | None = None
    velocity: np.ndarray | None = None
    output_is_velocity: bool = True
    source: str = "<memory>"
    joints: Mapping[str, np.ndarray] = field(default_factory=dict)
    shaft_rates: Mapping[str, float] = field(default_factory=dict)
    notes: Mapping[str, object] = field(default_factory=dict)
    torques: Mapping[str, np.ndarray] = field(default_factory=dict)
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def derived(self, key: object, make: Callable[[], np.ndarray]) -> np.ndarray:
        """A signal derived from this record, computed once (``make()``) and kept under ``key``."""
        if key not in self._derived:
            self._derived[key] = make()
        return self._derived[key]

    def __post_init__(self) -> None:
        u = np.asarray(self.u, dtype=float).ravel()
        y = np.asarray(self.y, dtype=float).ravel()
        if u.size != y.size:
            raise InputDataError(f"{self.source}: input {self.input_name!r} has {u.size} samples "
                                 f"but output {self.output_name!r} has {y.size}")
        if u.size < MIN_SAMPLES:
            raise InputDataError(f"{self.source}: only {u.size} samples; a diagnosis needs at "
                                 f"least {MIN_SAMPLES}")
        if not (np.isfinite(self.fs_hz) and self.fs_hz > 0):
            raise InputDataError(f"{self.source}: sample rate must be > 0, got {self.fs_hz!r}")
        _finite(u, self.input_name, self.source)
        _finite(y, self.output_name, self.source)
        if np.ptp(u) == 0:
            raise InputDataError(f"{self.source}: input {self.input_name!r} is constant "
                                 f"({u[0]:g}): nothing excites the model")
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "y", y)
        speeds = {}
        for name, x in dict(self.shaft_speeds_rad_s).items():
            speeds[name] = self._aux(x, f"{name} speed")
        object.__setattr__(self, "shaft_speeds_rad_s", speeds)
        unknown = [n for n in self.shaft_rates if n not in speeds]
        if unknown:
            raise InputDataError(f"{self.source}: shaft rate given for {unknown[0]!r}, which has no speed")
        if self.torsion is not None:
            object.__setattr__(self, "torsion", self._aux(self.torsion, "torsion"))
        if self.velocity is not None:
            object.__setattr__(self, "velocity", self._aux(self.velocity, "velocity"))
        object.__setattr__(self, "joints", {n: self._aux(x, f"twist of joint {n}")
                                            for n, x in dict(self.joints).items()})
        unknown = [n for n in self.torques if n not in speeds]
        if unknown:
            raise InputDataError(f"{self.source}: a torque is given on shaft {unknown[0]!r}, which has no speed")
        object.__setattr__(self, "torques", {n: self._aux(x, f"torque on {n}") for n, x in dict(self.torques).items()})

    def _aux(self, x: np.ndarray, name: str) -> np.ndarray:
        x = np.asarray(x, dtype=float).ravel()
        if x.size != self.y.size:
            raise InputDataError(f"{self.source}: {name} has {x.size} samples, expected {self.y.size}")
        _finite(x, name, self.source)
        return x

    def __len__(self) -> int:
        return int(self.y.size)

    @property
    def time_s(self) -> np.ndarray:
        """Sample times from 0 [s]."""
        return np.arange(self.y.size) / self.fs_hz

    @property
    def speed_for_sign(self) -> np.ndarray:
        """The velocity Coulomb friction follows (the output if none was given)."""
        return self.y if self.velocity is None else self.velocity


def _finite(x: np.ndarray, name: str, source: str) -> None:
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise InputDataError(f"{source}: {name} has {bad.size} non-finite values "
                             f"(first at sample {bad[0]})")


@dataclass(frozen=True)
class Split:
    """Estimation and held-out samples of a record of ``n`` samples.

    The record is cut into ``blocks`` equal blocks; each is estimated on its
    first ``fraction`` and held out on the rest.  One block is the classic
    split (the first ``fraction`` estimates, the tail validates); several
    interleave them, so that every operating point of a record whose speed
    changes is both estimated and validated ("compare like with like": a line
    whose amplitude and phase change with the speed cannot be judged at a
    speed it was not estimated at).  Filters and predictors run over the whole
    record; only the criterion and the figures pick their samples.  The runs,
    masks and indices are computed once (cached: the split is frozen).
    """

    n: int
    fraction: float
    blocks: int = 1
    keep: np.ndarray | None = field(default=None, compare=False)
    """Samples that count (the steady operating points); ``None``: all.  Transitions between
    operating points driven by an input the model does not have (a set-point step) are left out of
    both parts alike."""

    def __post_init__(self) -> None:
        if not 0.2 <= self.fraction <= 0.9:
            raise InputDataError(f"estimation fraction must be in [0.2, 0.9], got {self.fraction}")
        if self.blocks < 1 or self.n < 2 * self.blocks:
            raise InputDataError(f"cannot cut {self.n} samples into {self.blocks} validation blocks")

    def _runs(self) -> list[tuple[int, int, int]]:
        edges = np.round(np.linspace(0, self.n, self.blocks + 1)).astype(int)
        return [(int(a), int(a + round(self.fraction * (b - a))), int(b)) for a, b in zip(edges[:-1], edges[1:])]

    @cached_property
    def est_runs(self) -> list[tuple[int, int]]:
        return self._kept([(a, m) for a, m, _ in self._runs()])

    @cached_property
    def val_runs(self) -> list[tuple[int, int]]:
        return self._kept([(m, b) for _, m, b in self._runs() if b > m])

    def _kept(self, runs: list[tuple[int, int]]) -> list[tuple[int, int]]:
        if self.keep is None:
            return runs
        out = []
        for a, b in runs:
            k = np.concatenate(([False], np.asarray(self.keep[a:b], dtype=bool), [False])).astype(int)
            starts, stops = np.flatnonzero(np.diff(k) == 1), np.flatnonzero(np.diff(k) == -1)
            out += [(a + int(s), a + int(e)) for s, e in zip(starts, stops)]
        return out

    @cached_property
    def est_mask(self) -> np.ndarray:
        mask = np.zeros(self.n, dtype=bool)
        for a, b in self.est_runs:
            mask[a:b] = True
        mask.setflags(write=False)  # computed once (cached): nobody may change it
        return mask

    @cached_property
    def val_index(self) -> np.ndarray:
        index = np.concatenate([np.arange(a, b) for a, b in self.val_runs])
        index.setflags(write=False)  # computed once (cached): nobody may change it
        return index

    @cached_property
    def n_est(self) -> int:
        return int(sum(b - a for a, b in self.est_runs))

    def est_rows(self, t0: int) -> np.ndarray:
        """Estimation sample indices from ``t0`` on (the first ``t0`` lack their regressors)."""
        return np.flatnonzero(self.est_mask & (np.arange(self.n) >= t0))
