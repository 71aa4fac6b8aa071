"""Physical driveline parameters from the identified model.

Notes
-----
With the engine-side friction linearised to a slope :math:`\\beta`, the
two-mass oscillator's dyno-speed response to dyno torque is (method.md,
with the friction feedback added)

.. math::

    G_{11}(s) = -\\frac{1}{J_1}\\,
        \\frac{s^2 + \\frac{\\beta + d_s}{J_2} s + \\frac{c_s}{J_2}}
             {(s + p)(s^2 + 2\\zeta\\omega_0 s + \\omega_0^2)}

so its high-frequency gain is :math:`1/J_1`, its complex zeros are the
anti-resonance :math:`\\omega_a^2 = c_s/J_2` and its complex poles the
resonance :math:`\\omega_0^2 = c_s (J_1+J_2)/(J_1 J_2)` (for small
:math:`\\beta`; the real pole :math:`p \\approx \\beta/(J_1+J_2)` replaces
the integrator).  :func:`fit_response` fits gain, zeros, real pole and a
small delay (sampling) to the identified model's frequency response with the
complex pole pair fixed to the sorted driveline pair; :func:`parameters`
turns :math:`\\omega_0, \\zeta, \\omega_a` and a gain or known inertias into
:math:`J_1, J_2, c_s, d_s` using

.. math::

    \\frac{\\omega_0^2}{\\omega_a^2} = \\frac{J_1+J_2}{J_1},\\quad
    c_s = \\omega_a^2 J_2,\\quad
    d_s = 2\\zeta\\omega_0 \\frac{J_1 J_2}{J_1+J_2}.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import least_squares

from online_id.errors import EstimationError


@dataclass(frozen=True)
class ResponseFit:
    """Gain, anti-resonance and real pole fitted to a frequency response."""

    gain: float  # high-frequency gain 1/J1 [1/(kg m^2)]
    fa_hz: float
    zeta_a: float
    pole_hz: float
    delay_s: float
    rms_log_error: float


@dataclass(frozen=True)
class DrivelineParameters:
    """Resonance, damping and the physical two-mass parameters."""

    f0_hz: float
    zeta: float
    fa_hz: float | None
    J1: float | None
    J2: float | None
    c_s: float | None
    d_s: float | None
    source: str  # which inputs gave the inertias

    def as_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in asdict(self).items()}


def frequency_response(b: np.ndarray, a: np.ndarray, f_hz: np.ndarray, dt: float) -> np.ndarray:
    """``B(q^-1)/A(q^-1)`` evaluated at ``q = exp(j 2 pi f dt)``."""
    zinv = np.exp(-2j * np.pi * np.asarray(f_hz) * dt)
    num = np.polyval(np.asarray(b)[::-1], zinv)
    den = np.polyval(np.asarray(a)[::-1], zinv)
    return num / den


def response_grid(f0_hz: float, nyquist_hz: float, other_poles, n: int = 200) -> np.ndarray:
    """Frequencies for :func:`fit_response`: 0.35 f0 to 2.5 f0 (below 0.8 Nyquist), log-spaced.

    Frequencies within 5 % of a lightly damped (zeta < 0.15) complex pole of
    ``other_poles`` (the non-driveline poles: spurious pole-zero pairs leave
    wiggles in the response) are left out.
    """
    f = np.geomspace(0.35 * f0_hz, min(2.5 * f0_hz, 0.8 * nyquist_hz), n)
    keep = np.ones(f.shape, bool)
    for q in other_poles:
        if q.kind == "complex" and q.zeta < 0.15:
            keep &= np.abs(f - q.f_hz) > 0.05 * q.f_hz
    return f[keep]


def fit_response(
    f_hz: np.ndarray, response: np.ndarray, f0_hz: float, zeta: float, *, fa_guess_hz: float | None = None
) -> ResponseFit:
    """Fit the two-mass structure to a measured/identified frequency response.

    The complex pole pair is fixed to ``(f0_hz, zeta)``; gain, zeros, the real
    pole and a delay are free.  The error is the complex log ratio
    (log-magnitude and phase), so every frequency weighs alike.
    """
    f_hz = np.asarray(f_hz, dtype=float)
    response = np.asarray(response, dtype=complex)
    ok = np.isfinite(response) & (np.abs(response) > 0)
    f_hz, response = f_hz[ok], response[ok]
    if f_hz.size < 8:
        raise EstimationError("too few frequency points to fit the anti-resonance")
    s = 2j * np.pi * f_hz
    w0 = 2 * np.pi * f0_hz
    log_meas = np.log(response)

    def resid(x: np.ndarray) -> np.ndarray:
        return _log_residual(x, s, w0, zeta, log_meas)

    def jac(x: np.ndarray) -> np.ndarray:
        return _log_residual_jacobian(x, s)

    # start: gain from the highest frequencies, anti-resonance from the notch
    wa0 = 2 * np.pi * (fa_guess_hz if fa_guess_hz else 0.8 * f0_hz)
    below = f_hz < f0_hz
    if np.any(below):
        mag = np.abs(response[below]) * f_hz[below]
        wa0 = 2 * np.pi * f_hz[below][int(np.argmin(mag))]
    hi = f_hz > 1.5 * f0_hz
    g0 = float(np.median(np.abs(response[hi]) * 2 * np.pi * f_hz[hi])) if np.any(hi) else 1.0
    best = None
    for za0 in (0.02, 0.08):
        x0 = np.array([np.log(max(g0, 1e-9)), wa0, za0, 0.05 * w0, 0.0])
        lo, up = _bounds(w0)
        x0 = np.clip(x0, np.array(lo) + 1e-12, np.array(up) - 1e-12)
        try:
            sol = least_squares(resid, x0, jac=jac, bounds=(lo, up), x_scale="jac", max_nfev=400)
        except (ValueError, FloatingPointError):
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        raise EstimationError("the frequency-response fit of the anti-resonance failed")
    log_g, wa, za, p, tau = best.x
    rms = float(np.sqrt(np.mean(best.fun**2)))
    return ResponseFit(float(np.exp(log_g)), float(wa / (2 * np.pi)), float(za), float(p / (2 * np.pi)), float(tau), rms)


def _bounds(w0: float) -> tuple[list[float], list[float]]:
    """Bounds of ``x = (log gain, wa, zeta_a, real pole, delay)`` in :func:`fit_response`."""
    return [-np.inf, 0.1 * w0, 0.0, 0.0, -0.05], [np.inf, 0.999 * w0, 0.9, 0.9 * w0, 0.05]


def _log_residual(x: np.ndarray, s: np.ndarray, w0: float, zeta: float, log_meas: np.ndarray) -> np.ndarray:
    """Log-magnitude and wrapped phase of the two-mass model over the response (see :func:`fit_response`)."""
    log_g, wa, za, p, tau = x
    num = s**2 + 2 * za * wa * s + wa**2
    model = -np.exp(log_g) * num / ((s + p) * (s**2 + 2 * zeta * w0 * s + w0**2)) * np.exp(-s * tau)
    d = np.log(model) - log_meas
    return np.concatenate((d.real, (d.imag + np.pi) % (2 * np.pi) - np.pi))


def _log_residual_jacobian(x: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Derivatives of :func:`_log_residual` by ``x`` (the phase's wrapping is locally the identity)."""
    _, wa, za, p, _ = x
    num = s**2 + 2 * za * wa * s + wa**2
    d = np.column_stack([np.ones_like(s), (2 * za * s + 2 * wa) / num, 2 * wa * s / num, -1.0 / (s + p), -s])
    return np.vstack((d.real, d.imag))


def response_sensitivity(f_hz: np.ndarray, response: np.ndarray, fit: ResponseFit, f0_hz: float,
                         zeta: float) -> tuple[np.ndarray, np.ndarray]:
    """How the anti-resonance and gain of :func:`fit_response` move with the response and the fixed pole pair.

    Returns ``(D, E)``: ``D`` (2 x 2m) maps a change of the log response,
    stacked as ``[Re d log H; Im d log H]`` over the ``m`` frequencies, and
    ``E`` (2 x 2) a change of ``(f0_hz, zeta)``, to the change of
    ``(fa_hz, gain)``.

    Notes
    -----
    At the least-squares optimum :math:`x^*` of the residual
    :math:`r(x; \\log H, p)`, the implicit function theorem (the Gauss-Newton
    linearisation) gives :math:`dx = -(J^T J)^{-1} J^T (\\partial r/\\partial
    \\log H\\, d\\log H + \\partial r/\\partial p\\, dp)` with :math:`J =
    \\partial r/\\partial x` (central differences); a parameter held on a bound
    of the fit does not move.  :math:`\\partial r/\\partial \\log H = -I`.
    """
    f_hz = np.asarray(f_hz, dtype=float)
    response = np.asarray(response, dtype=complex)
    s = 2j * np.pi * f_hz
    w0 = 2 * np.pi * f0_hz
    log_meas = np.log(response)
    x = np.array([np.log(fit.gain), 2 * np.pi * fit.fa_hz, fit.zeta_a, 2 * np.pi * fit.pole_hz, fit.delay_s])
    lo, up = (np.array(b, dtype=float) for b in _bounds(w0))
    step = 1e-6 * np.maximum(np.abs(x), np.array([1.0, w0, 0.01, w0, 1e-3]))
    free = (x - lo > 2 * step) & (up - x > 2 * step)
    J = np.empty((2 * f_hz.size, x.size))
    for i in range(x.size):
        dx = np.zeros(x.size)
        dx[i] = step[i]
        J[:, i] = (_log_residual(x + dx, s, w0, zeta, log_meas) - _log_residual(x - dx, s, w0, zeta, log_meas)) / (2 * step[i])
    Jf = J[:, free]
    solve = np.zeros((x.size, 2 * f_hz.size))
    solve[free] = np.linalg.pinv(Jf.T @ Jf) @ Jf.T  # dx per unit -dr
    dr_dp = np.empty((2 * f_hz.size, 2))
    for i, (h_f, h_z) in enumerate(((1e-6 * f0_hz, 0.0), (0.0, 1e-6 * max(zeta, 1e-3)))):
        hp = _log_residual(x, s, 2 * np.pi * (f0_hz + h_f), zeta + h_z, log_meas)
        hm = _log_residual(x, s, 2 * np.pi * (f0_hz - h_f), zeta - h_z, log_meas)
        dr_dp[:, i] = (hp - hm) / (2 * (h_f + h_z))
    to_out = np.array([[0.0, 1.0 / (2 * np.pi), 0.0, 0.0, 0.0], [fit.gain, 0.0, 0.0, 0.0, 0.0]])
    return to_out @ solve, -(to_out @ solve @ dr_dp)


PHYSICAL = ("f0_hz", "zeta", "c_s", "d_s", "J1", "J2")


def parameter_jacobian(f0_hz: float, zeta: float, fa_hz: float | None, gain: float | None,
                       **inertias: float | None) -> np.ndarray:
    """``d (f0, zeta, c_s, d_s, J1, J2) / d (f0, zeta, fa, gain)`` of :func:`parameters` (central differences).

    Rows of parameters that :func:`parameters` leaves None are NaN; columns
    of inputs that are None are zero.
    """
    v = np.array([f0_hz, zeta, np.nan if fa_hz is None else fa_hz, np.nan if gain is None else gain])

    def out(x: np.ndarray) -> np.ndarray:
        d = parameters(x[0], x[1], None if np.isnan(x[2]) else float(x[2]),
                       None if np.isnan(x[3]) else float(x[3]), **inertias)
        return np.array([np.nan if getattr(d, k) is None else float(getattr(d, k)) for k in PHYSICAL])

    jac = np.zeros((len(PHYSICAL), 4))
    for i in range(4):
        if np.isnan(v[i]):
            continue
        h = 1e-6 * max(abs(v[i]), 1e-9)
        dv = np.zeros(4)
        dv[i] = h
        jac[:, i] = (out(v + dv) - out(v - dv)) / (2 * h)
    return jac


def parameters(
    f0_hz: float,
    zeta: float,
    fa_hz: float | None,
    gain: float | None,
    *,
    J1: float | None = None,
    J2: float | None = None,
    J_total: float | None = None,
) -> DrivelineParameters:
    """Physical parameters from resonance, damping, anti-resonance and gain.

    Known inertias take precedence over the identified gain, which moves with
    the operating point (seed paper, section 4):

    * ``J1`` and ``J2`` given: only the poles are used;
    * ``J1`` (dyno data sheet) or ``J_total`` (coast-down) given: poles and
      anti-resonance;
    * nothing given: poles, anti-resonance and the high-frequency gain
      ``1/J1``.
    """
    w0 = 2 * np.pi * f0_hz
    ratio = None  # (J1 + J2) / J1 = w0^2 / wa^2
    if fa_hz is not None and 0 < fa_hz < f0_hz:
        ratio = (f0_hz / fa_hz) ** 2
    if J1 is not None and J2 is not None:
        source = "J1 and J2 given"
    elif J1 is not None and ratio is not None:
        J2 = J1 * (ratio - 1.0)
        source = "J1 given, anti-resonance"
    elif J2 is not None and ratio is not None:
        J1 = J2 / (ratio - 1.0)
        source = "J2 given, anti-resonance"
    elif J_total is not None and ratio is not None:
        J1 = J_total / ratio
        J2 = J_total - J1
        source = "J1+J2 given, anti-resonance"
    elif gain is not None and gain > 0 and ratio is not None:
        J1 = 1.0 / gain
        J2 = J1 * (ratio - 1.0)
        source = "identified gain and anti-resonance"
    else:
        return DrivelineParameters(f0_hz, zeta, fa_hz, J1, J2, None, None, "poles only")
    jt = J1 + J2
    j_red = J1 * J2 / jt
    c_s = w0**2 * j_red
    d_s = 2 * zeta * w0 * j_red
    return DrivelineParameters(f0_hz, zeta, fa_hz, J1, J2, c_s, d_s, source)
