"""ARMAX model structure shared by every estimator.

Notes
-----
The model is, with the backward shift operator :math:`q^{-1}`,

.. math::

    A(q) y(t) = B(q) u(t) + C(q) e(t)

    A(q) = 1 + a_1 q^{-1} + \\dots + a_{na} q^{-na}

    B(q) = q^{-nk} (b_0 + b_1 q^{-1} + \\dots + b_{nb-1} q^{-nb+1})

    C(q) = 1 + c_1 q^{-1} + \\dots + c_{nc} q^{-nc}

(MATLAB's ``armax`` convention: ``nb`` counts coefficients, ``nk`` is the
input delay in samples).  The parameter vector and the regressor are

.. math::

    \\theta = [a_1 \\dots a_{na}, b_0 \\dots b_{nb-1}, c_1 \\dots c_{nc}]^T

    \\varphi(t) = [-y(t-1) \\dots -y(t-na), u(t-nk) \\dots u(t-nk-nb+1),
                  \\varepsilon(t-1) \\dots \\varepsilon(t-nc)]^T

so that :math:`y(t) = \\varphi(t)^T \\theta + e(t)`.  An optional constant
term (``offset=True``) appends a 1 to the regressor and a constant to
:math:`\\theta`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from online_id.errors import ConfigError


@dataclass(frozen=True)
class ArmaxOrders:
    """Orders of an ARMAX model (see module notes for the convention)."""

    na: int
    nb: int
    nc: int
    nk: int = 1
    offset: bool = False

    def __post_init__(self) -> None:
        for name in ("na", "nb", "nc"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 0:
                raise ConfigError(f"ARMAX order {name} must be an integer >= 0, got {value!r}")
        if self.na + self.nb == 0:
            raise ConfigError("ARMAX orders na and nb cannot both be 0")
        if not isinstance(self.nk, (int, np.integer)) or self.nk < 0:
            raise ConfigError(f"ARMAX input delay nk must be an integer >= 0, got {self.nk!r}")

    @property
    def n_params(self) -> int:
        """Length of the parameter vector theta."""
        return self.na + self.nb + self.nc + (1 if self.offset else 0)

    @property
    def max_lag(self) -> int:
        """Largest lag that appears in the regressor."""
        return max(self.na, self.nk + self.nb - 1, self.nc, 0)

    def split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Polynomials ``(A, B, C)`` as coefficient arrays in powers of q^-1.

        ``A`` and ``C`` start with the leading 1; ``B`` includes the ``nk``
        leading zeros, so ``scipy.signal.lfilter(B, A, u)`` simulates the model.
        """
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta has shape {theta.shape}, expected ({self.n_params},)")
        a = np.concatenate(([1.0], theta[: self.na]))
        b = np.concatenate((np.zeros(self.nk), theta[self.na : self.na + self.nb]))
        c = np.concatenate(([1.0], theta[self.na + self.nb : self.na + self.nb + self.nc]))
        return a, b, c
