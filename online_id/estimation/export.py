"""The identified models as plain data (polynomials, sample time, delay, units), and as python-control systems.

Notes
-----
Each operating point's model is MATLAB's ``idpoly`` form

.. math::

    A(q^{-1})\\, y(t) = B(q^{-1})\\, u(t) + C(q^{-1})\\, e(t),
    \\qquad \\mathrm{var}\\, e = \\lambda

with the coefficient vectors in increasing powers of :math:`q^{-1}`:
``A = [1, a1, ..., a_na]``, ``C = [1, c1, ..., c_nc]`` and ``B`` with the
input delay as ``nk`` leading zeros (``B = [0, b1, ...]`` for ``nk = 1``),
exactly as ``idpoly(A, B, C, 1, 1, lambda, Ts)`` takes them.  ``y`` is the
dyno speed [rad/s] and ``u`` the dyno torque [Nm] (positive brakes), both as
deviations from the operating point's means (``output_offset``,
``input_offset``).  As a transfer function in :math:`z`:
:math:`G(z) = B(z^{-1}) / A(z^{-1})`, i.e. numerator and denominator padded
to one length ``L`` and read as coefficients of :math:`z^{L-1}, \\dots, z^0`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from online_id.errors import InputDataError

FORM = "A(q) y(t) = B(q) u(t) + C(q) e(t); A, B, C in increasing powers of q^-1 (MATLAB idpoly)"
INPUT = ("dyno_torque", "Nm")
OUTPUT = ("dyno_speed", "rad/s")
KEYS = ("A", "B", "C", "sample_time_s", "input_delay_samples", "noise_variance")


def point_model(point) -> dict:
    """The model of one :class:`~online_id.estimation.identification.PointResult` as plain data (see notes).

    ``A``, ``B``, ``C`` are the model as identified; ``A_sim``, ``B_sim`` the
    model that ``compare`` simulates (the order-line pole-zero pairs the
    torque does not drive removed, unstable poles reflected into the unit
    circle with the same magnitude response): stable, for simulating the
    torque-to-speed response elsewhere.
    """
    fit = point.fit
    y0, u0 = point.offsets
    a_sim, b_sim, _, _ = simulation_polynomials(point)
    roots = np.roots(fit.A) if fit.A.size > 1 else np.zeros(0)
    return {
        "form": FORM,
        "A": [float(x) for x in fit.A], "B": [float(x) for x in fit.B], "C": [float(x) for x in fit.C],
        "A_sim": [float(x) for x in np.trim_zeros(a_sim, "b")] or [1.0],
        "B_sim": [float(x) for x in b_sim[:max(len(np.trim_zeros(b_sim, "b")), fit.orders.nk + 1)]],
        "unstable_poles": int(np.count_nonzero(np.abs(roots) > 1.0)),
        "sample_time_s": float(point.dt), "input_delay_samples": int(fit.orders.nk),
        "noise_variance": float(fit.V),
        "input": INPUT[0], "input_unit": INPUT[1], "output": OUTPUT[0], "output_unit": OUTPUT[1],
        "input_offset": float(u0), "output_offset": float(y0),
        "engine_speed_rpm": float(point.speed_rpm),
        "t_start_s": float(point.plateau.t_start_s), "t_end_s": float(point.plateau.t_end_s),
    }


def simulation_polynomials(point) -> tuple[np.ndarray, np.ndarray, int, int]:
    """``(A_sim, B_sim, pairs cancelled, poles reflected)``: the stable torque-to-speed model ``compare``
    simulates (see :func:`~online_id.estimation.validation.cancel_pairs`, ``stable_theta``)."""
    from online_id.analysis.poles import SPEED_DEPENDENT
    from online_id.estimation.validation import cancel_pairs, stable_theta

    fit = point.fit
    theta, n_cancelled = cancel_pairs(fit, [q.z for q in point.poles if q.cls == SPEED_DEPENDENT])
    theta, n_reflected = stable_theta(theta, fit.orders)
    a_sim, b_sim, _ = fit.orders.split(theta)
    return a_sim, b_sim, n_cancelled, n_reflected


def z_polynomials(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``num(q^-1)/den(q^-1)`` as coefficients in descending powers of ``z`` (both padded to one length)."""
    num = np.atleast_1d(np.asarray(num, dtype=float))
    den = np.atleast_1d(np.asarray(den, dtype=float))
    n = max(num.size, den.size)
    return np.pad(num, (0, n - num.size)), np.pad(den, (0, n - den.size))


def check_model(model: Mapping, where: str = "model") -> None:
    """Raise :class:`InputDataError` naming the key when ``model`` lacks a polynomial or the sample time."""
    for key in ("A", "B", "C", "sample_time_s"):
        if key not in model:
            raise InputDataError(f"{where}: expected the key {key!r} of an exported model, but it is missing")
    a = np.atleast_1d(np.asarray(model["A"], dtype=float))
    if a.size == 0 or a[0] != 1.0:
        raise InputDataError(f"{where}: expected A to start with 1 (monic, powers of q^-1), got {a[:1].tolist()}")
    if not float(model["sample_time_s"]) > 0:
        raise InputDataError(f"{where}: expected sample_time_s > 0, got {model['sample_time_s']!r}")


def transfer_functions(model: Mapping, simulation: bool = False):
    """``(G, H)``: python-control discrete transfer functions ``B/A`` (torque -> speed) and ``C/A`` (noise).

    ``simulation``: ``G`` of the stable simulation model ``B_sim/A_sim``
    instead (``H`` stays ``C/A``).  Needs python-control (``pip install
    online-id[control]``).
    """
    try:
        import control
    except ImportError as err:
        raise InputDataError("python-control is not installed: pip install control (or online-id[control])") from err
    check_model(model)
    dt = float(model["sample_time_s"])
    num, den = (model["B_sim"], model["A_sim"]) if simulation else (model["B"], model["A"])
    g = control.tf(*z_polynomials(num, den), dt,
                   inputs=str(model.get("input", INPUT[0])), outputs=str(model.get("output", OUTPUT[0])))
    h = control.tf(*z_polynomials(model["C"], model["A"]), dt, inputs="e", outputs=str(model.get("output", OUTPUT[0])))
    return g, h


def models_of_document(doc: Mapping) -> list[dict]:
    """The per-point models of an ``identify --json`` document (``operating_points[k]["model"]``)."""
    points = doc.get("operating_points") if isinstance(doc, Mapping) else None
    if not isinstance(points, list):
        raise InputDataError("expected an identify --json document with \"operating_points\"")
    out = []
    for k, p in enumerate(points):
        m = p.get("model") if isinstance(p, Mapping) else None
        if m is None:
            continue
        check_model(m, f"operating_points[{k}].model")
        out.append(dict(m))
    return out
