"""The effect library: model extensions the diagnosis can fit.

Each effect is a real change of the model that the identification fits:

==============================  =============================================
kind                            extension
==============================  =============================================
rotation_order_disturbance      :math:`\\sin, \\cos(o\\,\\theta_s(t - l))`
                                regressors at the first two lags of B,
                                :math:`\\theta_s = \\int \\omega_s dt`
fixed_frequency_disturbance     :math:`\\sin, \\cos(2\\pi f t)`, ``f`` refined, and
                                the causal band-pass at ``f`` of the residual
                                the line was found in, at two lags a quarter
                                period apart (:func:`band_past`)
additional_mode                 ``na`` and ``nb`` raised by 2 (one pole pair)
backlash                        dead-zone feature :math:`\\mathrm{clip}(\\varphi
                                - \\varphi_0, \\pm g/2)` of the torsion, width
                                ``g`` and centre by grid search
sensor_delay                    input and output shifted by ``d`` samples
coulomb_friction                :math:`\\mathrm{sign}(v(t - l))` regressors
absolute_value_sensor           Wiener model :math:`y = |x|` (see
                                :mod:`online_id.diagnose.wiener`)
==============================  =============================================

The lags ``l`` of the input-like regressors are those of ``B``
(``nk .. nk+nb-1``): a torque that adds to the input passes through the same
dynamics.  Parameter searches hold ``C`` at the current model's polynomial so
that each trial is one linear least-squares problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.signal import butter, iirpeak, lfilter
from scipy.optimize import linear_sum_assignment, minimize_scalar

from online_id.diagnose.data import DiagnoseData, Split
from online_id.diagnose.model import Structure, fit_structure, lag_matrix

ORDER_STEP = 0.5
BAND_Q = 8.0
"""Quality factor of the band-pass that follows a narrow-band line (:func:`band_past`)."""
BAND_QS = (8.0, 16.0, 32.0, 64.0)
"""Quality factors tried for a line fixed in Hz: the narrower its wander, the narrower the band that follows
it with the least noise."""
SCHEDULE_QUANTILES = (5.0, 50.0, 95.0)


def shaft_angle(speed_rad_s: np.ndarray, fs_hz: float) -> np.ndarray:
    """Shaft angle [rad] integrated from its speed (trapezoidal rule, 0 at the start)."""
    s = np.asarray(speed_rad_s, dtype=float)
    return np.concatenate(([0.0], np.cumsum(0.5 * (s[1:] + s[:-1])))) / fs_hz


def speed_hats(data: DiagnoseData) -> np.ndarray:
    """Piecewise-linear weights ``(n, k)`` over the first shaft's speed averaged over 1 s (they sum to 1).

    Knots at the 5, 50 and 95 % quantiles of the speed; one constant column when the speed spans less
    than 10 % of its mean (one operating point) or no shaft speed is known.
    """
    n = len(data)
    speeds = list(data.shaft_speeds_rad_s.values())
    if not speeds:
        return np.ones((n, 1))
    # the operating point, not the ripple the excitation puts on the speed: weights that followed the
    # ripple modulated the line with it, and that modulation, integrated through 1/A, lowered the
    # simulation fit of true lines
    w = uniform_filter1d(np.asarray(speeds[0], dtype=float), size=max(1, int(round(data.fs_hz))), mode="nearest")
    knots = np.percentile(w, SCHEDULE_QUANTILES)
    if not abs(np.mean(w)) > 0 or knots[-1] - knots[0] <= 0.1 * abs(np.mean(w)):
        return np.ones((n, 1))
    return np.column_stack([np.interp(w, knots, np.eye(knots.size)[j]) for j in range(knots.size)])


@dataclass(frozen=True)
class RotationOrder:
    """Disturbance at ``order`` times the rotation of ``shaft``, its amplitude and phase scheduled on speed.

    Notes
    -----
    A torque :math:`a \\sin(o\\theta_s + \\phi)` entering a shaft reaches the
    measured speed through the rig's dynamics at the line's frequency
    :math:`o\\,\\omega_s/2\\pi`, so its amplitude and phase in the output change
    with the operating point (near a mode by a factor of ten).  The columns are
    :math:`h_j(\\omega)\\sin(o\\theta_s(t - n_k))` and the same with cos, for
    piecewise-linear weights :math:`h_j` over the speed
    (:func:`speed_hats`): one amplitude and phase per knot, interpolated in
    between.
    """

    shaft: str
    order: float
    kind: str = "rotation_order_disturbance"

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        theta = self.order * shaft_angle(data.shaft_speeds_rad_s[self.shaft], data.fs_hz)
        # one lag (the first of B): several lags of one sinusoid are nearly collinear at one speed and
        # their coefficients extrapolate wildly to another; the speed schedule carries the change instead
        h = speed_hats(data)
        lag = max(int(np.asarray(lags)[0]), 0)
        x = np.column_stack((h * np.sin(theta)[:, None], h * np.cos(theta)[:, None]))
        out = np.zeros_like(x)
        out[lag:] = x[:x.shape[0] - lag]
        return out

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {"shaft": self.shaft, "order": float(self.order)}


def band_past(residual: np.ndarray, freq_hz: float, fs_hz: float, first_lag: int = 1,
              q: float = BAND_Q) -> list[np.ndarray]:
    """The causal band-pass (quality ``q``) of ``residual`` at ``freq_hz``, at lags ``first_lag`` and a
    quarter period later: two regressors that predict a narrow-band disturbance from its own past."""
    b, a = iirpeak(freq_hz, q, fs=fs_hz)
    bp = lfilter(b, a, np.nan_to_num(np.asarray(residual, dtype=float)))
    quarter = max(1, int(round(fs_hz / (4.0 * freq_hz))))
    return [np.concatenate((np.zeros(k), bp[:-k])) for k in (first_lag, first_lag + quarter)]


@dataclass(frozen=True)
class FixedFrequency:
    """Disturbance at ``freq_hz``: a sinusoid, and with ``residual`` (the one-step residual of the model the
    line was found in, full length) its band-pass past (:func:`band_past`, quality ``q``), which follows a
    line whose amplitude and phase wander (a narrow-band torque: a fan, a pump, a supply's ripple) where one
    sinusoid of constant phase over the record would not."""

    freq_hz: float
    kind: str = "fixed_frequency_disturbance"
    residual: np.ndarray | None = field(default=None, compare=False, repr=False)
    q: float = field(default=BAND_Q, compare=False)

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        w = 2.0 * np.pi * self.freq_hz * data.time_s
        cols = [np.sin(w), np.cos(w)]
        if self.predictor_cols:  # the residual belongs to its record: on another, the sinusoid alone
            cols += (band_past(self.residual, self.freq_hz, data.fs_hz, q=self.q)
                     if self.residual.size == data.y.size else [np.zeros(data.y.size)] * 2)
        return np.column_stack(cols)

    @property
    def predictor_cols(self) -> int:
        """Trailing columns that predict from the measured residual (left out of a simulation)."""
        return 2 if self.residual is not None else 0

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {"freq_hz": float(self.freq_hz)}


@dataclass(frozen=True)
class BacklashTerm:
    """Dead zone of width ``gap`` centred at ``center`` on the torsion proxy.

    The feature :math:`\\mathrm{clip}(\\varphi - \\varphi_0, -g/2, g/2)` is
    :math:`\\varphi - \\mathrm{dz}(\\varphi)`, the part of the torsion that
    transmits no torque; its coefficient corrects the linear spring.
    """

    gap: float
    center: float
    kind: str = "backlash"
    joint: str = ""

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        h = np.clip(twist(data, self.joint) - self.center, -0.5 * self.gap, 0.5 * self.gap)
        return lag_matrix(h, lags)

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {"gap_rad": float(self.gap), **({"joint": self.joint} if self.joint else {})}


@dataclass(frozen=True)
class LinearTorsion:
    """The torsion proxy itself as a regressor: the reference a backlash term is judged against.

    The proxy carries information from a second sensor (the engine speed), so
    a dead-zone feature of it is credited only with what it adds beyond the
    linear proxy.
    """

    kind: str = "linear_torsion"
    joint: str = ""

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        return lag_matrix(twist(data, self.joint), lags)

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {}


@dataclass(frozen=True)
class ShaftTorque:
    """A measured torque acting on ``shaft`` (``data.torques``) at the lags of ``B``: an input of the shaft's
    channel besides the record's input."""

    shaft: str
    kind: str = "shaft_torque"

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        return lag_matrix(data.torques[self.shaft], lags)

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {}


@dataclass(frozen=True)
class CoulombTerm:
    """Friction force :math:`F_c\\,\\mathrm{sign}(v)` entering like the input."""

    on_output: bool
    lags: tuple[int, ...]
    kind: str = "coulomb_friction"

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        return lag_matrix(np.sign(data.speed_for_sign), np.asarray(self.lags))

    def output_static(self) -> tuple[object, np.ndarray] | None:
        return (np.sign, np.asarray(self.lags)) if self.on_output else None

    def params(self) -> dict:
        return {}


def twist(data: DiagnoseData, joint: str = "") -> np.ndarray:
    """The twist across ``joint`` (``data.joints``), or the record's torsion proxy for ``""``."""
    return data.joints[joint] if joint else data.torsion


def slip_sign(phi: np.ndarray, fs_hz: float) -> np.ndarray:
    """The smoothed sign of a joint's relative speed (the rate of its twist ``phi``), causal.

    The rate is low-passed (second-order Butterworth at fs/8, causal: a regressor at lag 1 must not hold
    the sample it predicts) and passed through :math:`\\tanh(v / v_0)`, where :math:`v_0` is the noise
    left in the low-passed rate: the rate's RMS above fs/4 (differentiated encoder quantisation and speed
    noise, white there) scaled to the low-pass's band.  Where the joint really slips the speed is many
    :math:`v_0` and the feature is its sign; noise alone does not flip it.
    """
    return _sign_of(slip_rate(phi, fs_hz))


def _sign_of(v: np.ndarray) -> np.ndarray:
    return np.tanh(v) if np.all(np.isfinite(v)) else np.sign(v)


def joint_slip_sign_of(data: DiagnoseData, joint: str) -> np.ndarray:
    """:func:`slip_sign` of ``joint``'s twist, computed once per record and joint."""
    return data.derived(("slip_sign", joint), lambda: _sign_of(joint_slip_rate(data, joint)))


def joint_slip_rate(data: DiagnoseData, joint: str) -> np.ndarray:
    """:func:`slip_rate` of ``joint``'s twist, computed once per record and joint."""
    return data.derived(("slip_rate", joint), lambda: slip_rate(twist(data, joint), data.fs_hz))


def slip_rate(phi: np.ndarray, fs_hz: float) -> np.ndarray:
    """A joint's relative speed low-passed (causal) and in units of its noise :math:`v_0` (see
    :func:`slip_sign`); infinite where the rate has no noise to measure."""
    v = np.diff(np.asarray(phi, dtype=float), prepend=phi[0]) * fs_hz
    v_lp = lfilter(*butter(2, 0.25), v)
    hi = v - lfilter(*butter(2, 0.5), v)
    v0 = float(np.sqrt(np.mean(hi**2) * 0.125 / 0.25))
    with np.errstate(divide="ignore", invalid="ignore"):
        return v_lp / v0 if v0 > 0 else np.sign(v_lp) * np.inf


@dataclass(frozen=True)
class LinearSlip:
    """A joint's low-passed relative speed (:func:`slip_rate`) itself at the lags of ``B``: with the linear
    twist, the reference a joint's Coulomb friction is judged against, so that the friction is credited only
    with the sign's nonlinearity, not with the linear dynamics the smoothed sign also carries."""

    joint: str
    lags: tuple[int, ...]
    kind: str = "linear_slip"

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        v = joint_slip_rate(data, self.joint)
        return lag_matrix(np.where(np.isfinite(v), v, 0.0), np.asarray(self.lags))

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {}


@dataclass(frozen=True)
class JointCoulomb:
    """Coulomb friction in a joint: :math:`F_c` times the smoothed sign of the joint's relative speed
    (:func:`slip_sign` of its twist), at the lags of ``B``.

    On a rig turning one way the output speed never reverses, so friction that follows the sign of the
    speed is a constant there; friction in a joint (a coupling, a gear mesh) follows the relative motion
    of its two sides, which reverses with every oscillation of the joint.
    """

    joint: str
    lags: tuple[int, ...]
    kind: str = "coulomb_friction"

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        return lag_matrix(joint_slip_sign_of(data, self.joint), np.asarray(self.lags))

    def output_static(self) -> None:
        return None

    def params(self) -> dict:
        return {"joint": self.joint}


# -- parameter searches --------------------------------------------------------

def _loss(data: DiagnoseData, s: Structure, split: Split, C: np.ndarray) -> float:
    return fit_structure(data, s, split, C_fixed=C).V_est


def friction_lags(s: Structure) -> tuple[int, ...]:
    """The lags of ``B``, at least 1: at lag 0 a friction (or slip) regressor holds the predicted speed."""
    return tuple(int(l) for l in np.maximum(s.input_lags, 1))


def coulomb_structure(data: DiagnoseData, s: Structure, joint: str = "") -> Structure:
    """Structure with a Coulomb friction term (lags of ``B``, at least 1): in ``joint`` (the sign of its
    relative speed) if named, else on the sign of the velocity."""
    lags = friction_lags(s)
    if joint:
        return s.with_term(JointCoulomb(joint, lags))
    on_output = data.velocity is None and data.output_is_velocity
    return s.with_term(CoulombTerm(on_output, lags))


def search_delay(data: DiagnoseData, s: Structure, split: Split, C: np.ndarray,
                 hint: int, max_delay: int) -> Structure:
    """Best sensor delay (samples, negative = input delayed) by least squares."""
    lo = min(-2, hint - 2)
    hi = max(2, hint + 2)
    lo, hi = max(lo, -max_delay), min(hi, max_delay)
    base = s.delay
    best, best_v = s, np.inf
    for d in range(lo, hi + 1):
        trial = replace(s, delay=base + d)
        v = _loss(data, trial, split, C)
        if v < best_v:
            best, best_v = trial, v
    return best


def search_frequency(data: DiagnoseData, s: Structure, split: Split, C: np.ndarray,
                     f0_hz: float, half_width_hz: float) -> Structure:
    """Refine a fixed-frequency disturbance around ``f0_hz`` (grid, then bounded 1-D search)."""
    nyq = 0.5 * data.fs_hz
    lo, hi = max(f0_hz - half_width_hz, 1e-3), min(f0_hz + half_width_hz, 0.999 * nyq)
    grid = np.linspace(lo, hi, 31)
    losses = [_loss(data, s.with_term(FixedFrequency(f)), split, C) for f in grid]
    i = int(np.argmin(losses))
    step = grid[1] - grid[0]
    res = minimize_scalar(lambda f: _loss(data, s.with_term(FixedFrequency(f)), split, C),
                          bounds=(max(grid[i] - step, lo), min(grid[i] + step, hi)),
                          method="bounded", options={"xatol": 1e-4 * max(f0_hz, 1.0)})
    f = float(res.x) if res.fun <= losses[i] else float(grid[i])
    return s.with_term(FixedFrequency(f))


def search_backlash(data: DiagnoseData, s: Structure, split: Split, C: np.ndarray, joint: str = "") -> Structure:
    """Dead-zone width and centre on the twist of ``joint`` (``""``: the torsion proxy) by grid search
    (``s`` holds the linear twist)."""
    phi = twist(data, joint)[split.est_mask]
    lo, hi = np.percentile(phi, [2.0, 98.0])
    span = max(hi - lo, 1e-12)
    best, best_v = s, np.inf
    for center in lo + span * np.linspace(0.2, 0.8, 7):
        for gap in span * np.geomspace(0.03, 0.6, 12):
            trial = s.with_term(BacklashTerm(float(gap), float(center), joint=joint))
            v = _loss(data, trial, split, C)
            if v < best_v:
                best, best_v = trial, v
    return best


def mode_structure(s: Structure) -> Structure:
    """One more pole pair (and two more numerator coefficients)."""
    return replace(s, na=s.na + 2, nb=s.nb + 2)


def resolved(z: complex) -> bool:
    """Whether discrete pole ``z`` is one of a complex pair the record resolves as a mode: off the real
    axis, and its natural frequency :math:`|\\ln z| f_s / 2\\pi` below the Nyquist frequency
    (:math:`|\\ln z| < \\pi`).

    A negative real pole (:math:`\\ln z = \\ln|z| + j\\pi`) or a heavily damped pair near
    :math:`z = -1` maps to a "frequency" at or above the Nyquist frequency, even above the sample rate
    for :math:`|z|` near 0: an alternation of the equation error, not an oscillation the data hold.
    """
    return abs(z.imag) > 1e-9 and z != 0 and abs(np.log(complex(z))) < np.pi


def new_mode(A_old: np.ndarray, A_new: np.ndarray, fs_hz: float) -> tuple[float, float]:
    """Frequency [Hz] and damping ratio of the pole pair that ``A_new`` adds to ``A_old``.

    The poles of ``A_new`` are matched one to one to the nearest poles of ``A_old`` (least total distance
    in the z-plane); of the unmatched ones, the resolved complex pair (:func:`resolved`) farthest from every
    old pole is the added mode.  NaN, NaN when the added poles hold none: what the extra poles took is no
    mode below the Nyquist frequency (a negative real pole, an alternation near ``z = -1``).
    """
    def roots(A: np.ndarray) -> np.ndarray:
        return (np.roots(A) if A.size > 1 else np.zeros(0)).astype(complex)

    old, new = roots(A_old), roots(A_new)
    added = new
    if old.size and new.size:
        rows, _ = linear_sum_assignment(np.abs(new[:, None] - old[None, :]))
        added = np.delete(new, rows)
    cand = np.array([z for z in added if z.imag > 0 and resolved(z)], dtype=complex)
    if cand.size == 0:
        return float("nan"), float("nan")
    s_new = np.log(cand) * fs_hz
    pick = s_new[0]
    if old.size:
        s_old = np.log(old[np.abs(old) > 1e-9]) * fs_hz
        if s_old.size:
            pick = s_new[int(np.argmax(np.min(np.abs(s_new[:, None] - s_old[None, :]), axis=1)))]
    return float(np.abs(pick) / (2.0 * np.pi)), float(-pick.real / np.abs(pick))
