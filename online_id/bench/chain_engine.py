"""The torque of a four-stroke piston engine as a function of its crank angle (720 deg cycle).

Each cylinder is a slider crank (crank radius ``r``, rod ``l``, ``lam = r / l``).  Its gas torque is
``(p - p0) A ds/dphi`` with ``phi`` the crank angle from that cylinder's firing top dead centre.

Notes
-----
Piston travel from top dead centre, in units of ``r``, and its derivatives::

    s(phi)   = 1 - cos(phi) + (1 - sqrt(1 - lam^2 sin^2 phi)) / lam
    s'(phi)  = sin(phi) (1 + lam cos(phi) / sqrt(1 - lam^2 sin^2 phi))

Volume over the swept volume ``V = 1 / (eps - 1) + s / 2`` (``eps`` the compression ratio).  The
pressure (over the intake pressure ``p0``) is polytropic: compression from bottom dead centre
(``phi = -180``) with exponent ``n_c``, expansion from top dead centre with exponent ``n_e`` from
``loss * p_tdc`` (heat and blow-by losses: a motored cylinder absorbs work), and ``p0`` during the
exhaust and intake strokes.  A fired cylinder adds the pressure of its combustion: the burnt fraction
of a Wiebe function ``x_b = 1 - exp(-5 ((phi - phi_s) / dphi)^3)`` times a pressure that expands
polytropically from top dead centre.  The reciprocating mass adds ``-m r^2 s'' s' omega^2`` (a
360 deg periodic torque).

The cylinders fire evenly, every ``720 / N`` degrees.  Identical cylinders sum to the orders
``k N / 2`` only (the declared compression orders); one cylinder that differs (compresses more or
less, misfires) adds its own torque's spectrum: every half order 0.5, 1, 1.5, ...
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from online_id.errors import ConfigError

TABLE_POINTS = 5760
"""Samples of a 720 deg table (0.125 deg)."""


@dataclass(frozen=True)
class Engine:
    """A four-stroke engine's crank-angle torque (see module notes).

    ``pulse_nm`` is the amplitude of the engine's line at its firing order ``N / 2`` when every
    cylinder is alike (the declared compression line); ``compression_scale`` multiplies each
    cylinder's compression pressure (in firing sequence); ``indicated_nm`` is the mean torque of the
    combustion with every cylinder firing (0: a motored engine), ``firing`` which cylinders fire.
    """

    cylinders: int
    pulse_nm: float
    compression_ratio: float = 10.0
    rod_ratio: float = 0.3
    n_compression: float = 1.32
    n_expansion: float = 1.36
    expansion_loss: float = 0.93
    compression_scale: tuple[float, ...] = ()
    indicated_nm: float = 0.0
    firing: tuple[bool, ...] = ()
    mass_nm_at_1000rpm: float = 0.0
    friction_nm: float = 0.0
    viscous_nm_s: float = 0.0

    def __post_init__(self) -> None:
        if not 1 <= self.cylinders <= 12:
            raise ConfigError(f"engine: cylinders must be 1..12 (got {self.cylinders})")
        for name, seq in (("compression_scale", self.compression_scale), ("firing", self.firing)):
            if seq and len(seq) != self.cylinders:
                raise ConfigError(f"engine: {name} needs one entry per cylinder ({self.cylinders}), got {len(seq)}")
        if self.pulse_nm < 0 or self.indicated_nm < 0 or not 0 < self.rod_ratio < 1 or self.compression_ratio <= 1:
            raise ConfigError(f"engine: pulse_nm, indicated_nm >= 0, 0 < rod_ratio < 1, compression_ratio > 1 ({self})")

    @property
    def pulses_per_rev(self) -> float:
        """Compression pulses per crank revolution: ``N / 2`` (the declared order)."""
        return self.cylinders / 2.0

    def tdc_deg(self) -> np.ndarray:
        """Crank angle of each cylinder's firing top dead centre, in firing sequence."""
        return np.arange(self.cylinders) * 720.0 / self.cylinders

    def _grid_deg(self) -> np.ndarray:
        return np.arange(TABLE_POINTS) * 720.0 / TABLE_POINTS

    def _per_cylinder(self, one) -> np.ndarray:
        """``one(phi_deg)`` of each cylinder on the 720 deg grid: shape (cylinders, TABLE_POINTS)."""
        grid = self._grid_deg()
        return np.array([one((grid - tdc + 360.0) % 720.0 - 360.0) for tdc in self.tdc_deg()])

    def _compression(self, phi_deg: np.ndarray) -> np.ndarray:
        """Gas torque of one motored cylinder over ``A r p0`` at ``phi`` in [-360, 360)."""
        s, ds = slider_crank(np.radians(phi_deg), self.rod_ratio)
        v = 1.0 / (self.compression_ratio - 1.0) + s / 2.0
        v_bdc, v_tdc = 1.0 / (self.compression_ratio - 1.0) + 1.0, 1.0 / (self.compression_ratio - 1.0)
        p_tdc = (v_bdc / v_tdc) ** self.n_compression
        p = np.ones_like(phi_deg)
        comp = (phi_deg >= -180.0) & (phi_deg < 0.0)
        exp_ = (phi_deg >= 0.0) & (phi_deg < 180.0)
        p[comp] = (v_bdc / v[comp]) ** self.n_compression
        p[exp_] = np.maximum(self.expansion_loss * p_tdc * (v_tdc / v[exp_]) ** self.n_expansion, 1.0)
        return (p - 1.0) * ds

    def _combustion(self, phi_deg: np.ndarray) -> np.ndarray:
        """Torque of one cylinder's combustion pressure (unscaled) at ``phi`` in [-360, 360)."""
        s, ds = slider_crank(np.radians(phi_deg), self.rod_ratio)
        v = 1.0 / (self.compression_ratio - 1.0) + s / 2.0
        v_tdc = 1.0 / (self.compression_ratio - 1.0)
        start, duration = -8.0, 55.0
        x = np.clip((phi_deg - start) / duration, 0.0, None)
        burnt = 1.0 - np.exp(-5.0 * x ** 3)
        p = np.where((phi_deg > start) & (phi_deg < 180.0), burnt * (v_tdc / v) ** self.n_expansion, 0.0)
        return p * ds

    def _mass(self, phi_deg: np.ndarray) -> np.ndarray:
        """Torque of one cylinder's reciprocating mass over ``m r^2 omega^2``."""
        phi = np.radians(phi_deg)
        lam = self.rod_ratio
        _s, ds = slider_crank(phi, lam)
        root = np.sqrt(1.0 - lam ** 2 * np.sin(phi) ** 2)
        d2s = np.cos(phi) + lam * (np.cos(phi) ** 2 - np.sin(phi) ** 2) / root + lam ** 3 * np.sin(phi) ** 2 * np.cos(
            phi) ** 2 / root ** 3
        return -d2s * ds

    def gas_table(self) -> np.ndarray:
        """Gas torque [Nm] over one 720 deg cycle (:data:`TABLE_POINTS` samples) of crank angle."""
        comp = self._per_cylinder(self._compression)
        even = comp.sum(axis=0)
        line = _order_amplitude(even, self.pulses_per_rev)
        scale = self.pulse_nm / line if line > 0 else 0.0
        comp_scale = np.asarray(self.compression_scale or (1.0,) * self.cylinders)
        total = scale * (comp_scale[:, None] * comp).sum(axis=0)
        if self.indicated_nm > 0:
            comb = self._per_cylinder(self._combustion)
            mean_all = comb.sum(axis=0).mean()
            fire = np.asarray(self.firing or (True,) * self.cylinders, dtype=float)
            total = total + self.indicated_nm / mean_all * (fire[:, None] * comb).sum(axis=0)
        return total

    def mass_table(self) -> np.ndarray:
        """Reciprocating-mass torque over omega^2 [Nm s^2] over one 720 deg cycle of crank angle."""
        if self.mass_nm_at_1000rpm == 0 or self.pulse_nm == 0:
            return np.zeros(TABLE_POINTS)
        mass = self._per_cylinder(self._mass).sum(axis=0)
        line = max(np.max(np.abs(mass)), 1e-12)
        w1000 = 1000.0 * np.pi / 30.0
        return self.mass_nm_at_1000rpm / (line * w1000 ** 2) * mass


def slider_crank(phi: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Piston travel from top dead centre ``s`` [r] and ``ds/dphi`` at crank angle ``phi`` [rad]."""
    root = np.sqrt(1.0 - lam ** 2 * np.sin(phi) ** 2)
    s = 1.0 - np.cos(phi) + (1.0 - root) / lam
    ds = np.sin(phi) * (1.0 + lam * np.cos(phi) / root)
    return s, ds


def order_amplitudes(table: np.ndarray, orders: np.ndarray) -> np.ndarray:
    """Amplitudes of a 720 deg table's lines at crank ``orders`` (multiples of 0.5)."""
    spec = np.fft.rfft(table) / table.size
    idx = np.rint(2 * np.asarray(orders, dtype=float)).astype(int)
    return 2.0 * np.abs(spec[idx])


def _order_amplitude(table: np.ndarray, order: float) -> float:
    return float(order_amplitudes(table, np.array([order]))[0])
