"""Discrete poles -> frequency and damping, and sorting them across operating points.

Notes
-----
A discrete pole :math:`z` maps to :math:`s = \\ln(z) / T_s` (python-control's
``damp`` semantics): natural frequency :math:`|s| / 2\\pi` [Hz] and damping
ratio :math:`\\zeta = -\\Re(s)/|s|`.  Special cases handled explicitly:

* :math:`z = 0` (a pure delay): :math:`s = -\\infty`, reported as frequency
  ``inf`` and damping 1;
* negative real :math:`z`: :math:`\\ln z = \\ln|z| + j\\pi`, i.e. an
  oscillation at the Nyquist frequency; reported as a "complex" pole at
  :math:`|s|/2\\pi` with its damping.

Sorting (the seed paper's method): the driveline's poles stay put when the
engine speed changes; the spurious poles move with it.  A complex pole whose
frequency sits on an engine order line (``order * rpm / 60``, orders in
half steps) at its operating point is *speed dependent*; the pair that is
found at the same frequency at (nearly) every operating point is the
*driveline* mode; further pairs that are invariant too are reported as
*invariant* (a second mode, a structural resonance); the rest are *other*.

A pole pair on an order line with almost no damping (``|zeta| <=
LINE_ZETA``) is a *rotation line*: the ARMAX part absorbed a periodic
torque locked to the rotation.  It is never a candidate for the driveline or
an invariant mode, even where every operating point runs at one speed (then
an order line does not move and would otherwise look invariant), and the
sorting lists what it set aside.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass, field, replace

import numpy as np

DRIVELINE = "driveline"
SPEED_DEPENDENT = "speed_dependent"
INVARIANT = "invariant"
REAL = "real"
OTHER = "other"
LINE_ZETA = 0.02  # an order line is an (almost) undamped oscillator; a driveline mode is damped more


@dataclass(frozen=True)
class Pole:
    """A discrete pole (one per conjugate pair) with its continuous meaning."""

    z: complex
    f_hz: float
    zeta: float
    kind: str  # "complex" or "real"
    cls: str = OTHER
    order: float | None = None

    def as_dict(self) -> dict:
        out = {
            "f_hz": _finite(self.f_hz),
            "zeta": _finite(self.zeta),
            "class": self.cls,
            "z_re": float(self.z.real),
            "z_im": float(self.z.imag),
        }
        if self.order is not None:
            out["order"] = self.order
        return out


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def damp(z: np.ndarray | complex, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Natural frequency [Hz] and damping ratio of discrete poles ``z``.

    ``z = 0`` gives ``(inf, 1.0)``; negative real ``z`` is an oscillation at
    the Nyquist frequency (see module notes).
    """
    z = np.atleast_1d(np.asarray(z, dtype=complex))
    freq = np.empty(z.shape)
    zeta = np.empty(z.shape)
    zero = np.abs(z) == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.log(np.where(zero, 1.0, z)) / dt
    mag = np.abs(s)
    freq[:] = mag / (2.0 * np.pi)
    with np.errstate(divide="ignore", invalid="ignore"):
        zeta[:] = np.where(mag > 0, -s.real / mag, -1.0)
    # z == 1 exactly: an integrator, zero frequency; call it zeta = -1 (marginal, no decay)
    freq[zero] = np.inf
    zeta[zero] = 1.0
    return freq, zeta


try:  # numpy's compiled eigenvalue routine, which np.linalg.eigvals calls after its argument checks
    from numpy.linalg._umath_linalg import eigvals as _eigvals
except ImportError:  # pragma: no cover - another numpy layout: the public function
    _eigvals = None


def polynomial_roots(a: np.ndarray) -> np.ndarray:
    """Roots of polynomial ``a`` (complex), as ``np.roots`` gives them (eigenvalues of the companion matrix),
    without its argument checks: the service computes them at every publication.

    numpy's eigenvalue routine is called directly (about half the cost of ``np.linalg.eigvals``, which
    checks and converts around the same call); where it gives no finite result, ``np.linalg.eigvals``
    runs and raises as ``np.roots`` does."""
    nz = np.flatnonzero(a)
    if nz.size == 0:
        return np.array([], dtype=complex)
    trailing = len(a) - 1 - int(nz[-1])  # each trailing zero coefficient is a root at 0
    a = a[nz[0]:nz[-1] + 1]
    n = len(a) - 1
    roots = np.zeros(trailing, dtype=complex)
    if n < 1:
        return roots
    comp = np.zeros((n, n))
    comp[0, :] = -a[1:] / a[0]
    comp[np.arange(1, n), np.arange(n - 1)] = 1.0
    w = _eigvals(comp, signature="d->D") if _eigvals is not None and np.isfinite(comp[0]).all() else None
    if w is None or not np.isfinite(w).all():
        w = np.linalg.eigvals(comp).astype(complex)
    return np.concatenate([w, roots])



def poles_of(a: np.ndarray, dt: float, tol_imag: float = 1e-9) -> list[Pole]:
    """Poles of ``A(q^-1)`` (coefficients in powers of q^-1), one per conjugate pair."""
    return poles_of_roots(polynomial_roots(np.asarray(a, dtype=float)), dt, tol_imag)


def poles_of_roots(roots: np.ndarray, dt: float, tol_imag: float = 1e-9) -> list[Pole]:
    """:func:`poles_of` from the roots of ``A`` (:func:`polynomial_roots`)."""
    out: list[Pole] = []
    for z in roots.tolist():  # the service computes this at every publication: scalar math, no numpy per root
        if z.imag < -tol_imag:
            continue
        real = abs(z.imag) <= tol_imag
        if z == 0:
            f, zt = math.inf, 1.0
        else:
            s = cmath.log(z) / dt
            mag = abs(s)
            f, zt = mag / (2.0 * math.pi), (-s.real / mag if mag > 0 else -1.0)
        kind = "real" if real and z.real >= 0 else "complex"
        out.append(Pole(complex(z.real, 0.0) if real else z, f, zt, kind, REAL if kind == "real" else OTHER))
    out.sort(key=lambda p: (p.kind != "complex", p.f_hz))
    return out


def order_of(f_hz: float, speed_rpm: float, *, max_order: float = 12.0, tol_pct: float = 2.5, tol_hz: float = 0.4) -> float | None:
    """The engine order (in half steps) whose line ``order*rpm/60`` passes through ``f_hz``, or None."""
    rev_hz = speed_rpm / 60.0
    if rev_hz <= 0 or not np.isfinite(f_hz):
        return None
    order = round(2.0 * f_hz / rev_hz) / 2.0
    if order < 0.5 or order > max_order:
        return None
    line = order * rev_hz
    if abs(f_hz - line) <= max(tol_hz, tol_pct / 100.0 * line):
        return order
    return None


def rotation_line(f_hz: float, zeta: float, rates_hz: dict[str, float], *, line_zeta: float = LINE_ZETA,
                  step: float = 0.5, max_order: float = 40.0, tol_pct: float = 2.5,
                  tol_hz: float = 0.4) -> tuple[str, float] | None:
    """``(shaft, order)`` when a pole pair is a rotation line: damped no more than ``line_zeta`` and at a
    multiple (``step``: half orders) of a shaft's rotation rate [Hz] (within ``tol_pct`` or ``tol_hz``);
    the smallest order over the shafts.  ``None`` otherwise."""
    if not (np.isfinite(f_hz) and np.isfinite(zeta) and abs(zeta) <= line_zeta):
        return None
    best = None
    for shaft, r in rates_hz.items():
        if not r > 0:
            continue
        k = round(f_hz / r / step) * step
        if 0 < k <= max_order and abs(f_hz - k * r) <= max(tol_hz, tol_pct / 100.0 * k * r):
            if best is None or k < best[1]:
                best = (shaft, float(k))
    return best


@dataclass(frozen=True)
class ModeSummary:
    """The invariant driveline mode found across operating points."""

    f0_hz: float
    zeta: float
    f0_std_hz: float
    zeta_std: float
    per_point: tuple[tuple[float, float] | None, ...]  # (f, zeta) per operating point or None
    n_points: int


@dataclass(frozen=True)
class SetAsideLine:
    """A rotation-order line the model holds as a pole pair, set aside from the modes."""

    order: float
    f_hz: float
    zeta: float
    n_points: int
    declared: bool = False  # a harmonic of the declared compression pulses (expected, not reported)

    def text(self) -> str:
        return (f"a pole pair at {self.f_hz:.2f} Hz with damping {self.zeta:.4f} sits on order {self.order:g} of "
                f"the rotation at {self.n_points} operating point(s): a rotation-order line (a periodic torque "
                "locked to the shaft), set aside from the modes; it is not the driveline resonance")


@dataclass
class PoleSorting:
    """Result of :func:`sort_poles`: classified poles per point and the driveline mode."""

    poles: list[list[Pole]]
    driveline: ModeSummary | None
    invariant_modes: list[ModeSummary] = field(default_factory=list)
    lines: list[SetAsideLine] = field(default_factory=list)


def is_rotation_line(p: Pole, line_zeta: float = LINE_ZETA) -> bool:
    """A pole on an order line (``p.order`` set) with almost no damping: a rotation-order line."""
    return p.kind == "complex" and p.order is not None and abs(p.zeta) <= line_zeta


def set_aside_lines(poles_per_point: list[list[Pole]], line_zeta: float = LINE_ZETA,
                    pulses_per_rev: float | None = None) -> list[SetAsideLine]:
    """The rotation lines of :func:`is_rotation_line`, one per order, over the operating points; those at
    a multiple of ``pulses_per_rev`` are marked declared."""
    by_order: dict[float, list[Pole]] = {}
    for row in poles_per_point:
        for p in row:
            if is_rotation_line(p, line_zeta):
                by_order.setdefault(p.order, []).append(p)
    return [SetAsideLine(k, float(np.median([p.f_hz for p in ps])), float(np.median([p.zeta for p in ps])), len(ps),
                         bool(pulses_per_rev) and abs(k / pulses_per_rev - round(k / pulses_per_rev)) < 1e-9)
            for k, ps in sorted(by_order.items())]


def _cluster_modes(cands: list[list[Pole]], tol_pct: float, min_points: int) -> list[tuple[list[int | None], float]]:
    """Groups of poles (one index per point or None) with similar frequency across points."""
    flat = sorted({(p.f_hz) for pts in cands for p in pts})
    clusters: list[tuple[list[int | None], float]] = []
    used: set[tuple[int, int]] = set()
    # try every candidate as a seed, keep the best assignment for each seed
    seeds = []
    for f_seed in flat:
        members: list[int | None] = []
        for pts in cands:
            best, best_err = None, None
            for j, p in enumerate(pts):
                err = abs(p.f_hz - f_seed) / f_seed * 100.0
                if err <= tol_pct and (best_err is None or err < best_err):
                    best, best_err = j, err
            members.append(best)
        count = sum(m is not None for m in members)
        if count >= min_points:
            fs = np.array([cands[i][m].f_hz for i, m in enumerate(members) if m is not None])
            zs = np.array([cands[i][m].zeta for i, m in enumerate(members) if m is not None])
            seeds.append((count, float(np.std(fs) / np.mean(fs)), float(np.median(zs)), f_seed, members))
    # most points first, then tightest, then least damped
    seeds.sort(key=lambda s: (-s[0], s[1], s[2]))
    for count, _spread, _z, f_seed, members in seeds:
        keys = {(i, m) for i, m in enumerate(members) if m is not None}
        if keys & used:
            continue
        used |= keys
        clusters.append((members, f_seed))
    return clusters


def _summarise(cands: list[list[Pole]], members: list[int | None]) -> ModeSummary:
    per = tuple((cands[i][m].f_hz, cands[i][m].zeta) if m is not None else None for i, m in enumerate(members))
    fs = np.array([p[0] for p in per if p is not None])
    zs = np.array([p[1] for p in per if p is not None])
    return ModeSummary(float(np.median(fs)), float(np.median(zs)), float(np.std(fs)), float(np.std(zs)), per, int(fs.size))


def sort_poles(
    poles_per_point: list[list[Pole]],
    speeds_rpm: list[float],
    *,
    band_hz: tuple[float, float] = (3.0, 120.0),
    pulses_per_rev: float | None = None,
    tol_pct: float = 3.0,
    max_zeta: float = 0.5,
    max_order_zeta: float = 0.2,
    max_freq_hz: float = np.inf,
    line_zeta: float = LINE_ZETA,
) -> PoleSorting:
    """Class every pole as driveline, invariant, speed dependent, real or other.

    Parameters
    ----------
    poles_per_point
        Poles of the model identified at each operating point.
    speeds_rpm
        Engine speed of each operating point.
    band_hz
        Frequency band in which the driveline mode is searched.
    pulses_per_rev
        Compression pulses per revolution when known (cylinders / 2 for a
        4-stroke engine); any half order is recognised either way.
    tol_pct
        How far (percent) an invariant pole may move between points.
    max_zeta
        Most damped pole that can be an invariant mode.
    max_order_zeta
        Most damped pole that can sit on an order line: a periodic
        disturbance is an (almost) undamped oscillator, so well damped or
        unstable poles near a line are fit artefacts, not orders.
    max_freq_hz
        Poles above this frequency (near Nyquist, where the anti-alias filter
        leaves no signal) are never put on an order line.
    line_zeta
        A pole on an order line damped no more than this is a rotation line
        (:func:`is_rotation_line`): never a mode candidate.
    """
    n_points = len(poles_per_point)
    marked: list[list[Pole]] = []
    for pts, rpm in zip(poles_per_point, speeds_rpm):
        row = []
        for p in pts:
            if p.kind != "complex":
                row.append(replace(p, cls=REAL))
                continue
            plausible = -0.02 < p.zeta < max_order_zeta and p.f_hz <= max_freq_hz
            order = order_of(p.f_hz, rpm) if plausible else None
            row.append(replace(p, cls=SPEED_DEPENDENT if order is not None else OTHER, order=order))
        marked.append(row)

    # candidates for invariant modes: lightly damped complex poles in the band;
    # order-line poles are candidates too, since an invariant mode may cross an order line at one point
    cand_idx = [
        [j for j, p in enumerate(row) if p.kind == "complex" and band_hz[0] <= p.f_hz <= band_hz[1]
         and 0.0 < p.zeta < max_zeta and not is_rotation_line(p, line_zeta)]
        for row in marked
    ]
    cands = [[marked[i][j] for j in idx] for i, idx in enumerate(cand_idx)]
    min_points = n_points if n_points <= 2 else max(2, int(np.ceil(0.6 * n_points)))
    clusters = _cluster_modes(cands, tol_pct, min_points)

    modes: list[tuple[ModeSummary, list[int | None]]] = []
    for members, _f in clusters:
        # a cluster whose members all sit on order lines is not invariant unless speeds are equal
        on_lines = [cands[i][m].order is not None for i, m in enumerate(members) if m is not None]
        speeds = [speeds_rpm[i] for i, m in enumerate(members) if m is not None]
        if all(on_lines) and (max(speeds) - min(speeds)) > 0.05 * max(speeds):
            orders = {cands[i][m].order for i, m in enumerate(members) if m is not None}
            if len(orders) == 1:
                continue
        modes.append((_summarise(cands, members), members))

    driveline = None
    invariant: list[ModeSummary] = []
    if modes:
        # the driveline: the invariant pair seen at most points; among equals the lowest frequency
        modes.sort(key=lambda m: (-m[0].n_points, m[0].f0_hz))
        best_n = modes[0][0].n_points
        top = [m for m in modes if m[0].n_points == best_n]
        top.sort(key=lambda m: m[0].f0_hz)
        drive, drive_members = top[0]
        driveline = drive
        for summary, members in modes:
            cls = DRIVELINE if members is drive_members else INVARIANT
            if cls == INVARIANT:
                invariant.append(summary)
            for i, m in enumerate(members):
                if m is not None:
                    j = cand_idx[i][m]
                    marked[i][j] = replace(marked[i][j], cls=cls, order=None)
    return PoleSorting(marked, driveline, invariant, set_aside_lines(marked, line_zeta, pulses_per_rev))


def modal_residue(a: np.ndarray, b: np.ndarray, z: complex, roots: np.ndarray | None = None) -> float:
    """Magnitude of the residue of :math:`B/A` at the pole ``z`` (``a``, ``b`` in powers of q^-1; ``roots``:
    the roots of ``a`` where they are at hand, :func:`polynomial_roots`).

    Notes
    -----
    With :math:`A(q^{-1}) = \\prod_j (1 - p_j q^{-1})`, the partial fraction
    of :math:`B/A` at a simple pole :math:`p_i` is :math:`r_i / (1 - p_i
    q^{-1})` with :math:`r_i = B(p_i^{-1}) / \\prod_{j \\ne i} (1 - p_j /
    p_i)`. It measures how much of the input-output response the mode
    carries, whatever its damping: a pole nearly cancelled by a zero of
    :math:`B` (a noise-model or nonlinearity artefact beside the real mode)
    has a small residue. Returns 0 for ``z = 0``.
    """
    if z == 0:
        return 0.0
    if roots is None:
        roots = np.roots(np.asarray(a, dtype=float))
    if roots.size == 0:
        return 0.0
    others = np.delete(roots, int(np.argmin(np.abs(roots - z))))
    q = 1.0 / z
    den = np.prod(1.0 - others * q)
    num = np.polyval(np.asarray(b, dtype=float)[::-1], q)  # B(q) = sum b_k q^k
    return float(abs(num / den)) if den != 0 else float("inf")


def pole_gradient(a: np.ndarray, z: complex, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of a pole's frequency [Hz] and damping with respect to ``a[1:]`` (see :func:`pole_std`).

    Infinite where the derivative does not exist (``z = 0``, a multiple root).
    """
    a = np.asarray(a, dtype=float)
    n = a.size - 1
    if n < 1 or z == 0:
        return np.full(max(n, 0), np.inf), np.full(max(n, 0), np.inf)
    dA = np.polyval(np.polyder(a), z)  # z^n + a1 z^(n-1) + ... : same order as np.polyval expects
    if dA == 0:
        return np.full(n, np.inf), np.full(n, np.inf)
    powers = z ** np.arange(n - 1, -1, -1)  # z^(n-k) for k = 1..n
    G = -powers / dA / (z * dt)  # d s / d a_k
    s = np.log(z) / dt
    x, y = s.real, s.imag
    r = abs(s)
    return (x * G.real + y * G.imag) / (2 * np.pi * r), (-(y**2) * G.real + x * y * G.imag) / r**3


def pole_std(a: np.ndarray, z: complex, cov_a: np.ndarray, dt: float) -> tuple[float, float]:
    """Standard deviations of a pole's frequency [Hz] and damping from the covariance of ``a``.

    Notes
    -----
    For :math:`A(z) = z^{n} + a_1 z^{n-1} + \\dots + a_n` with a simple root
    :math:`z_0`, :math:`\\partial z_0/\\partial a_k = -z_0^{n-k}/A'(z_0)`; with
    :math:`s = \\ln z / T_s = x + jy` and :math:`r = |s|`,
    :math:`\\partial f/\\partial(x, y) = (x, y)/(2\\pi r)` and
    :math:`\\partial \\zeta/\\partial(x, y) = (-y^2, xy)/r^3`.  First-order
    propagation: :math:`\\sigma_f^2 = g_f^T \\Sigma_a g_f`.
    """
    g_f, g_z = pole_gradient(a, z, dt)
    if g_f.size == 0 or not (np.all(np.isfinite(g_f)) and np.all(np.isfinite(g_z))):
        return float("inf"), float("inf")
    var_f = float(g_f @ cov_a @ g_f)
    var_z = float(g_z @ cov_a @ g_z)
    return float(np.sqrt(max(var_f, 0.0))), float(np.sqrt(max(var_z, 0.0)))
