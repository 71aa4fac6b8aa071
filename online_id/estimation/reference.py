"""The window a baseline cell was learned from, kept to ask later whether a change is the driveline's.

Notes
-----
An ARMAX model that does not fit the plant exactly (a shaft with backlash)
has a prediction-error criterion with several nearly equal minima. Their
resonances differ by 1-3 % and their damping by 30-40 %; which one the
warm-started refits follow is a matter of history. A cell learned while the
refits sat in one minimum, and an estimate that later moved to another, differ
by a percent at the same operating point with nothing changed in the
driveline. The criterion itself cannot always tell: on a simulated bench
with 0.59 mrad of backlash the minimum the refits found
after 2000 s (31.1 Hz) fits *every* window of that hour 0.5-1.9 % better
than the one its cells were learned in (30.8 Hz), before 2000 s as well;
while a genuine 5 % stiffness loss on another bench with backlash raised
the loss of the baseline's minimum by only 1.0 %. No tie on the loss
separates the two.

What separates them is the data the baseline was learned from. The window of
the cell's first estimates, those its frozen reference holds (:class:`ReferenceWindow`, 10 s of the
filtered, decimated dyno speed and torque, about 80 kB) is refitted from two
starts: its own solution, and the solution the window refits hold now
(:func:`refit_each`). If the driveline changed, the healthy data pull the
current solution back to the healthy resonance, and the change measured
*within one minimum* (the current estimate against the reference data in the
current minimum) is the change itself: on the evaluation's benches with
backlash, 1.7-5.6 % in frequency for 5-10 % stiffness losses and 31-60 % in
damping for +-50 % damping changes. If only the minimum changed, the
reference data in the current minimum give the current estimate again
(1017: 31.03-31.06 Hz against 31.06-31.20 Hz, where its cell was learned
at 30.75 Hz): the apparent change is within the tolerance, and the alarm is
withheld (:func:`judge`). The tolerance is the detector's dead band plus one
standard deviation of the difference of two single estimates (the current
one's own, and the cell's spread: 0.3 % in frequency on 1017), so that the
change must stand out of the dead band by more than the noise of the
comparison for the alarm to stand.

The fit must also be as good: the reference data must fit in the current
minimum within the tie of the second look (1 %) of their own minimum's
loss. Alone the loss cannot tell a change from a move of minimum (above),
but it catches a refit that stopped near its start: on a simulated bench
without backlash a -50 % damping change, refitted on the healthy
reference data, stayed at the changed damping (-1.7 % from the current
estimate) at a loss 6.1 % above the healthy minimum's; on the bench with
backlash above, the current minimum fits the reference data 1.7-2.0 % better
than their own.
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from online_id.analysis.poles import poles_of
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import ArmaxFit, fit_armax
from online_id.estimation.window import FIT_ERRORS, SOLVER

MAX_ZETA = 0.3  # a driveline pole is lightly damped: the candidates of the current minimum's pick


@dataclass(frozen=True)
class ReferenceWindow:
    """The window (``y`` dyno speed, ``u`` dyno torque, filtered and decimated) and window solution of a cell's
    first estimates, at ``speed_rpm`` and ``load_nm``, stream time ``t_s``."""

    y: np.ndarray
    u: np.ndarray
    solution: np.ndarray
    speed_rpm: float
    load_nm: float
    t_s: float

    def to_dict(self) -> dict:
        """JSON-ready: the samples as base64 of little-endian float32 (about 53 kB for 10 s at 500 Hz).

        Encoded once (the window never changes; the service snapshots its state every minute)."""
        return dict(self._saved)

    @cached_property
    def _saved(self) -> dict:
        return {"y": _pack(self.y), "u": _pack(self.u), "solution": [float(x) for x in self.solution],
                "speed_rpm": float(self.speed_rpm), "load_nm": float(self.load_nm), "t_s": float(self.t_s)}

    @classmethod
    def from_dict(cls, data: dict, n_params: int) -> ReferenceWindow | None:
        """The window saved by :meth:`to_dict`; None where it is malformed (a window is an aid, never required)."""
        try:
            y, u = _unpack(data["y"]), _unpack(data["u"])
            solution = np.asarray(data["solution"], dtype=float)
            speed, load, t = float(data["speed_rpm"]), float(data["load_nm"]), float(data["t_s"])
        except (KeyError, TypeError, ValueError):
            return None
        if (len(y) != len(u) or len(y) < 10 * n_params or solution.shape != (n_params,)
                or not (np.all(np.isfinite(y)) and np.all(np.isfinite(u)) and np.all(np.isfinite(solution)))
                or not all(math.isfinite(x) for x in (speed, load))):
            return None
        return cls(y, u, solution, speed, load, t)


def _pack(x: np.ndarray) -> str:
    return base64.b64encode(np.asarray(x, dtype="<f4").tobytes()).decode("ascii")


def _unpack(s: str) -> np.ndarray:
    raw = base64.b64decode(s.encode("ascii"), validate=True)
    if len(raw) % 4:
        raise ValueError("not a float32 array")
    return np.frombuffer(raw, dtype="<f4").astype(float)


def refit_each(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, starts: tuple) -> tuple[ArmaxFit | None, ...]:
    """A prediction-error fit of one window from each of ``starts`` (None where one fails); pure, for a worker."""
    out: list[ArmaxFit | None] = []
    for theta0 in starts:
        try:
            out.append(fit_armax(y, u, orders, theta0=np.asarray(theta0, dtype=float), solver=SOLVER))
        except FIT_ERRORS:
            out.append(None)
    return tuple(out)


@dataclass(frozen=True)
class Recheck:
    """What the reference window says in the current minimum.

    ``f0_hz``, ``zeta``: the driveline pole of the fit from the current
    solution (the lightly damped pair nearest the current estimate);
    ``loss_ratio``: its loss over that of the fit from the reference's own
    solution, less one; ``change``: the current estimate's relative change
    against it, of the quantity judged; ``withhold``: the change is within the
    tolerance and the loss within the tie.
    """

    f0_hz: float
    zeta: float
    loss_ratio: float
    change: float
    withhold: bool


def judge(fits: tuple[ArmaxFit | None, ...], dt: float, f0_hz: float, zeta: float, damping: bool,
          tolerance: float, tie: float) -> Recheck | None:
    """Judge an alarm by the reference window's fits ``(from its own solution, from the current one)``.

    ``f0_hz``, ``zeta``: the current estimate; ``damping``: the alarm is of
    the damping (else the frequency); ``tolerance``: the largest relative change withheld (see the module notes);
    ``tie``: the largest loss ratio (less one) of the fit from the current solution over that from the reference's
    own at which the alarm is withheld.
    None where a fit failed or has no lightly damped pole (the alarm stands).
    """
    if len(fits) != 2 or fits[0] is None or fits[1] is None or not (fits[0].V > 0 and math.isfinite(fits[1].V)):
        return None
    own, current = fits
    poles = [p for p in poles_of(current.A, dt) if p.kind == "complex" and 0.0 < p.zeta < MAX_ZETA]
    if not poles or not (math.isfinite(f0_hz) and math.isfinite(zeta)):
        return None
    pole = min(poles, key=lambda p: abs(p.f_hz - f0_hz))
    ratio = current.V / own.V - 1.0
    change = zeta / pole.zeta - 1.0 if damping else f0_hz / pole.f_hz - 1.0
    return Recheck(pole.f_hz, pole.zeta, ratio, change, abs(change) <= tolerance and ratio <= tie)
