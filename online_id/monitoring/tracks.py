"""Pole tracks across updates, classed online as driveline mode or speed dependent.

Notes
-----
**Matching.**  At each update the complex poles with frequency in
``[f_min_hz, f_max_hz]`` and damping in ``(-0.05, max_zeta)`` are matched to
the live tracks by the Hungarian method (``scipy.optimize.linear_sum_assignment``)
on the cost

.. math::

    c_{ij} = \\frac{|\\ln f_i - \\ln \\hat f_j|}{\\ln(1 + p/100)}
             + \\frac{|\\zeta_i - \\zeta_j|}{0.05}

where :math:`p` = ``max_jump_pct`` and :math:`\\hat f_j` is track
:math:`j`'s reference: the medians of its last 10 points (one stray pole
does not move it), carried to the new engine speed :math:`n` by the class
(:math:`o n / 60` on an order line, :math:`\\hat f_j (n / n_j)^{e_j}` with
the elasticity :math:`e_j` for another speed dependent track).  Pairs with
:math:`|\\ln f_i - \\ln \\hat f_j| > \\ln(1 + p/100)` are not matched.  An
unmatched pole starts a track; a track unseen for ``retire_s`` is retired
(a tentative one, with fewer than ``min_points`` points, after 1 s).

**Classification** over the track history (at most ``history`` updates):

* speed movement :math:`R = (n_{95} - n_{5}) / \\tilde n` (percentiles and
  median of the engine speed);
* engine order: :math:`o = \\operatorname{round}(2\\,\\operatorname{median}(60 f / n)) / 2`
  and the relative residual :math:`\\epsilon_o = \\operatorname{median}|60 f / (o n) - 1|`;
  on an order line when :math:`\\epsilon_o <` ``order_tol`` and the track is
  nearly undamped (median :math:`\\zeta <` ``max_order_zeta``; a periodic
  disturbance is an almost undamped oscillator);
* elasticity :math:`e = d\\ln f / d\\ln n`, the least-squares slope of
  :math:`\\ln f` on :math:`\\ln n`, with its standard error.

With movement (:math:`R \\ge` ``min_range``): on an order line and
:math:`|e - 1| < 0.25` -> speed dependent with that order; :math:`|e| <
e_{inv}` -> driveline (invariant); :math:`|e| > 2 e_{inv}` -> speed
dependent (friction slope, no order); else unknown.  Without movement: on an
order line -> speed dependent (confidence at most 0.6), else a provisional
driveline with confidence at most 0.3.

Confidence :math:`\\in [0, 1]` is the product of the persistence
:math:`\\min(1, N / N_{full})` (hits in the history), the movement
evidence :math:`\\min(1, R / R_{full})` and a fit term (how far :math:`e`
sits inside its class, how small :math:`\\epsilon_o` is).

**No flapping.** A class reached with confidence of at least ``lock`` is
kept until different evidence *with* speed movement reaches ``lock`` too;
inconclusive updates (no movement, too few points) leave it unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from online_id.analysis.poles import Pole
from online_id.monitoring.checks import integer, number
from online_id.errors import ConfigError

DRIVELINE = "driveline"
SPEED_DEPENDENT = "speed_dependent"
UNKNOWN = "unknown"


def small_median(values: list[float]) -> float:
    """``float(np.median(values))`` of a short list of floats, the same number, without numpy's cost per call (a
    track's reference is taken at every publication): the mean of the middle value or two, summed from 0.0 as
    numpy's mean sums (so -0.0 comes out 0.0); NaN where one is NaN."""
    xs = sorted(values)
    n = len(xs)
    if n == 0 or any(x != x for x in xs):
        return math.nan
    m = n // 2
    return 0.0 + xs[m] if n % 2 else (0.0 + xs[m - 1] + xs[m]) / 2.0


@dataclass(frozen=True)
class TrackHistory:
    """Read-only history of one track, oldest first."""

    t_s: np.ndarray
    speed_rpm: np.ndarray
    f_hz: np.ndarray
    zeta: np.ndarray


class Track:
    """One pole followed across updates (built and updated by :class:`PoleTracker`)."""

    def __init__(self, track_id: int, size: int) -> None:
        self.id = int(track_id)
        self._buf = np.full((4, size), np.nan)  # rows: t, speed, f, zeta (ring buffer)
        self._n = 0  # points stored in total (the ring keeps the last `size`)
        self.cls = UNKNOWN
        self.confidence = 0.0
        self.order: float | None = None
        self.elasticity = 0.0  # d ln f / d ln n from the last classification
        self.first_seen_s = math.nan
        self.last_seen_s = math.nan
        self.n_updates = 0  # tracker updates since the track started (hit rate = n_seen / n_updates)
        self.n_seen = 0
        self.next_classify_s = -math.inf

    # latest values
    @property
    def f_hz(self) -> float:
        return float(self._buf[2, (self._n - 1) % self._buf.shape[1]])

    @property
    def zeta(self) -> float:
        return float(self._buf[3, (self._n - 1) % self._buf.shape[1]])

    @property
    def speed_rpm(self) -> float:
        return float(self._buf[1, (self._n - 1) % self._buf.shape[1]])

    @property
    def history(self) -> TrackHistory:
        size = self._buf.shape[1]
        if self._n <= size:
            arr = self._buf[:, : self._n].copy()
        else:
            i = self._n % size
            arr = np.concatenate((self._buf[:, i:], self._buf[:, :i]), axis=1)
        arr.flags.writeable = False
        return TrackHistory(arr[0], arr[1], arr[2], arr[3])

    def _push(self, t: float, speed: float, f: float, zeta: float) -> None:
        self._buf[:, self._n % self._buf.shape[1]] = (t, speed, f, zeta)
        self._n += 1
        self.n_seen += 1
        self.last_seen_s = t
        self._set_ref()
        if not math.isfinite(self.first_seen_s):
            self.first_seen_s = t

    def _set_ref(self) -> None:
        """The reference: the medians of the last points' frequency, damping and speed (see :meth:`reference`)."""
        _t, speed, f, zeta = self._recent().tolist()
        self._ref = (small_median(f), small_median(zeta), small_median(speed))

    def _recent(self, k: int = 10) -> np.ndarray:
        """The last ``k`` points (rows t, speed, f, zeta)."""
        size = self._buf.shape[1]
        m = min(k, self._n, size)
        idx = (np.arange(self._n - m, self._n)) % size
        return self._buf[:, idx]

    def reference(self, speed_rpm: float) -> tuple[float, float]:
        """Expected (frequency, damping) at ``speed_rpm``, from the median of the last points.

        The frequency follows the class: the order line, the elasticity of a
        speed dependent track, or stays put.
        """
        f_ref, z_ref, n_ref = self._ref
        if self.cls == SPEED_DEPENDENT and self.order is not None and speed_rpm > 0:
            return self.order * speed_rpm / 60.0, z_ref
        if self.cls == SPEED_DEPENDENT and n_ref > 0 and speed_rpm > 0:
            return f_ref * (speed_rpm / n_ref) ** float(np.clip(self.elasticity, 0.0, 1.5)), z_ref
        return f_ref, z_ref

    def __repr__(self) -> str:
        order = f", order={self.order}" if self.order is not None else ""
        return (f"Track(id={self.id}, f_hz={self.f_hz:.2f}, zeta={self.zeta:.3f}, cls={self.cls!r}, "
                f"confidence={self.confidence:.2f}{order})")

    def to_dict(self) -> dict[str, Any]:
        h = self.history
        return {
            "id": self.id, "size": int(self._buf.shape[1]), "n_total": self._n,
            "t": h.t_s.tolist(), "speed": h.speed_rpm.tolist(), "f": h.f_hz.tolist(), "zeta": h.zeta.tolist(),
            "cls": self.cls, "confidence": self.confidence, "order": self.order, "elasticity": self.elasticity,
            "first_seen_s": self.first_seen_s, "last_seen_s": self.last_seen_s,
            "n_updates": self.n_updates, "n_seen": self.n_seen,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Track:
        tr = cls(int(d["id"]), int(d["size"]))
        rows = np.array([d["t"], d["speed"], d["f"], d["zeta"]], dtype=float).reshape(4, -1)
        m = rows.shape[1]
        n_total = int(d["n_total"])
        size = tr._buf.shape[1]
        for j in range(m):  # place so that index n_total-1 holds the newest point
            tr._buf[:, (n_total - m + j) % size] = rows[:, j]
        tr._n = n_total
        tr._set_ref()
        tr.cls = str(d["cls"])
        tr.confidence = float(d["confidence"])
        tr.order = None if d["order"] is None else float(d["order"])
        tr.elasticity = float(d["elasticity"])
        tr.first_seen_s = float(d["first_seen_s"])
        tr.last_seen_s = float(d["last_seen_s"])
        tr.n_updates = int(d["n_updates"])
        tr.n_seen = int(d["n_seen"])
        return tr


class PoleTracker:
    """Match poles between updates into tracks and class each track (see module notes).

    Parameters
    ----------
    dt
        Sample period of the model whose poles are tracked [s]; the upper
        frequency bound defaults to ``0.4 / dt``.
    max_jump_pct
        Largest relative frequency change between updates for a match [%].
    history
        Points kept per track for the classification.
    pulses_per_rev
        Compression pulses per revolution, when known; an order line at a
        multiple of it counts as stronger evidence.
    f_min_hz, f_max_hz
        Band of tracked poles (``f_max_hz`` None: ``0.4 / dt``).
    max_zeta
        Most damped pole that is tracked.
    retire_s
        A track unseen for this long is retired.
    min_points
        Points a track needs before it is classed.
    min_range, full_range
        Relative engine-speed movement below which the speed dependence is
        not judged, and at which the movement evidence is complete.
    e_invariant
        Largest elasticity :math:`|d\\ln f/d\\ln n|` of an invariant mode.
    order_tol
        Largest median relative distance to an order line.
    max_order_zeta
        Most damped track that can sit on an order line.
    lock
        Confidence at which a class is held against inconclusive evidence.
    """

    def __init__(
        self,
        *,
        dt: float,
        max_jump_pct: float = 5.0,
        history: int = 600,
        pulses_per_rev: float | None = None,
        f_min_hz: float = 3.0,
        f_max_hz: float | None = None,
        max_zeta: float = 0.5,
        retire_s: float = 10.0,
        min_points: int = 20,
        full_points: int = 100,
        min_range: float = 0.05,
        full_range: float = 0.2,
        e_invariant: float = 0.1,
        order_tol: float = 0.02,
        max_order_zeta: float = 0.1,
        lock: float = 0.8,
    ) -> None:
        def pos(name: str, v: float) -> float:
            return number("PoleTracker", name, v)

        self.dt = pos("dt", dt)
        self.max_jump_pct = pos("max_jump_pct", max_jump_pct)
        self.history = integer("PoleTracker", "history", history, minimum=10)
        self.pulses_per_rev = None if pulses_per_rev is None else pos("pulses_per_rev", pulses_per_rev)
        self.f_min_hz = pos("f_min_hz", f_min_hz)
        self.f_max_hz = 0.4 / self.dt if f_max_hz is None else pos("f_max_hz", f_max_hz)
        if self.f_max_hz <= self.f_min_hz:
            raise ConfigError(f"PoleTracker: expected f_max_hz > f_min_hz = {self.f_min_hz}, but got {self.f_max_hz}")
        self.max_zeta = pos("max_zeta", max_zeta)
        self.retire_s = pos("retire_s", retire_s)
        self.min_points = max(3, int(min_points))
        self.full_points = max(self.min_points, int(full_points))
        self.min_range = pos("min_range", min_range)
        self.full_range = max(pos("full_range", full_range), self.min_range)
        self.e_invariant = pos("e_invariant", e_invariant)
        self.order_tol = pos("order_tol", order_tol)
        self.max_order_zeta = pos("max_order_zeta", max_order_zeta)
        self.lock = pos("lock", lock)
        self._tracks: list[Track] = []
        self._next_id = 1
        self._gate = math.log1p(self.max_jump_pct / 100.0)

    # -- per update --------------------------------------------------------------------------------
    def update(self, *, t_s: float, speed_rpm: float, poles: Sequence[Pole]) -> None:
        """Match ``poles`` to the tracks, start new tracks, retire old ones, re-class."""
        cand = [p for p in poles if p.kind == "complex" and self.f_min_hz <= p.f_hz <= self.f_max_hz
                and -0.05 < p.zeta < self.max_zeta and math.isfinite(p.f_hz) and math.isfinite(p.zeta)]
        tracks = self._tracks
        matched_tracks: set[int] = set()
        used: set[int] = set()
        if cand and tracks:
            lf = np.log([p.f_hz for p in cand])
            zp = np.array([p.zeta for p in cand])
            ref = np.array([tr.reference(speed_rpm) for tr in tracks])
            lt = np.log(np.maximum(ref[:, 0], 1e-9))
            zt = ref[:, 1]
            dl = np.abs(lf[:, None] - lt[None, :])
            cost = dl / self._gate + np.abs(zp[:, None] - zt[None, :]) / 0.05
            big = 1e6
            cost = np.where(dl <= self._gate, cost, big)
            rows, cols = linear_sum_assignment(cost)
            for i, j in zip(rows, cols):
                if cost[i, j] < big:
                    tracks[j]._push(t_s, speed_rpm, cand[i].f_hz, cand[i].zeta)
                    matched_tracks.add(j)
                    used.add(i)
        for i, p in enumerate(cand):
            if i not in used:
                tr = Track(self._next_id, self.history)
                self._next_id += 1
                tr._push(t_s, speed_rpm, p.f_hz, p.zeta)
                tracks.append(tr)
        for tr in tracks:
            tr.n_updates += 1
        # tentative tracks (fewer than min_points) go after 1 s unseen, others after retire_s
        self._tracks = [tr for tr in tracks if t_s - tr.last_seen_s
                        <= (self.retire_s if tr.n_seen >= self.min_points else min(1.0, self.retire_s))]
        for tr in self._tracks:
            # re-class at most once a second once a track is established: the class rests on the
            # history (up to ``history`` points) and moves slowly, and the evidence costs ~0.3 ms a track
            if tr.last_seen_s == t_s and (tr.n_seen <= 2 * self.min_points or t_s >= tr.next_classify_s):
                tr.next_classify_s = t_s + 1.0
                self._classify(tr)

    # -- classification ----------------------------------------------------------------------------
    def _evidence(self, tr: Track) -> tuple[str, float, float | None, float, bool]:
        """(class, confidence, order, elasticity, moved) from the track's history."""
        h = tr.history
        n = h.f_hz.size
        if n < self.min_points:
            return UNKNOWN, 0.0, None, tr.elasticity, False
        speed = h.speed_rpm
        ok = speed > 0
        speed, f, zeta = speed[ok], h.f_hz[ok], h.zeta[ok]
        if speed.size < self.min_points:
            return UNKNOWN, 0.0, None, tr.elasticity, False
        persistence = min(1.0, n / self.full_points) * min(1.0, 1.5 * tr.n_seen / max(tr.n_updates, 1))
        med_n = float(np.median(speed))
        p5, p95 = np.percentile(speed, (5.0, 95.0))
        R = float((p95 - p5) / med_n)
        movement = min(1.0, R / self.full_range)
        # order line
        with np.errstate(over="ignore"):  # a restored track may hold any finite number (the state is not trusted)
            ratio = 60.0 * f / speed
        med_ratio = float(np.median(ratio))
        o = round(2.0 * med_ratio) / 2.0 if math.isfinite(med_ratio) else math.inf
        order = None
        fit_o = 0.0
        if 0.5 <= o <= 12.0 and float(np.median(zeta)) < self.max_order_zeta:
            eps = float(np.median(np.abs(ratio / o - 1.0)))
            if eps < self.order_tol:
                order = o
                fit_o = 1.0 - eps / self.order_tol
        pulse = self.pulses_per_rev is not None and order is not None and \
            abs(order / self.pulses_per_rev - round(order / self.pulses_per_rev)) < 1e-9
        if R < self.min_range:
            if order is not None:
                return SPEED_DEPENDENT, persistence * (0.6 if pulse else 0.5) * (0.5 + 0.5 * fit_o), order, 1.0, False
            return DRIVELINE, 0.3 * persistence, None, 0.0, False
        # elasticity: slope of ln f on ln n
        x = np.log(speed)
        y = np.log(f)
        xm = x - x.mean()
        sxx = float(xm @ xm)
        e = float(xm @ (y - y.mean()) / sxx)
        res = y - y.mean() - e * xm
        se = math.sqrt(float(res @ res) / max(x.size - 2, 1) / sxx)
        if order is not None and abs(e - 1.0) < 0.25:
            conf = persistence * (0.7 + 0.3 * movement) * (0.6 + 0.4 * fit_o)
            return SPEED_DEPENDENT, conf, order, e, True
        ae = abs(e) + se
        if ae < self.e_invariant:
            fit = 1.0 - (ae / self.e_invariant) ** 2
            conf = persistence * movement * (0.7 + 0.3 * fit)
            return DRIVELINE, conf, None, e, True
        if abs(e) - se > 2.0 * self.e_invariant:
            fit = min(1.0, (abs(e) - se) / (4.0 * self.e_invariant))
            conf = persistence * movement * (0.7 + 0.3 * fit)
            return SPEED_DEPENDENT, conf, None, e, True
        return UNKNOWN, 0.3 * persistence * movement, None, e, True

    def _classify(self, tr: Track) -> None:
        cls, conf, order, e, moved = self._evidence(tr)
        locked = tr.cls != UNKNOWN and tr.confidence >= self.lock
        if locked and cls != tr.cls and not (moved and conf >= self.lock):
            return  # a held class yields only to conclusive contrary evidence
        if locked and cls == tr.cls:
            # same class: keep the strongest evidence found so far (no confidence flapping)
            tr.confidence = max(tr.confidence, float(np.clip(conf, 0.0, 1.0)))
            tr.order = order if order is not None else tr.order
            if moved:
                tr.elasticity = e
            return
        tr.cls, tr.confidence, tr.order, tr.elasticity = cls, float(np.clip(conf, 0.0, 1.0)), order, e

    # -- results -----------------------------------------------------------------------------------
    @property
    def tracks(self) -> list[Track]:
        """Live tracks, oldest first (a new list; the tracks are the tracker's own)."""
        return list(self._tracks)

    def driveline(self, *, max_zeta: float = 0.3, tie: float = 0.05) -> Track | None:
        """The invariant, lightly damped (median damping below ``max_zeta``) track of highest confidence.

        Confidences within ``tie`` of the best count as equal; among them the
        lowest frequency wins.
        """
        cands = [tr for tr in self._tracks if tr.cls == DRIVELINE
                 and float(np.median(tr.history.zeta)) < max_zeta]
        if not cands:
            return None
        best = max(tr.confidence for tr in cands)
        top = [tr for tr in cands if tr.confidence >= best - tie]
        return min(top, key=lambda tr: tr.f_hz)

    def reset(self) -> None:
        """Forget all tracks."""
        self._tracks = []

    # -- persistence -------------------------------------------------------------------------------
    def params(self) -> dict[str, Any]:
        return {
            "dt": self.dt, "max_jump_pct": self.max_jump_pct, "history": self.history,
            "pulses_per_rev": self.pulses_per_rev, "f_min_hz": self.f_min_hz, "f_max_hz": self.f_max_hz,
            "max_zeta": self.max_zeta, "retire_s": self.retire_s, "min_points": self.min_points,
            "full_points": self.full_points, "min_range": self.min_range, "full_range": self.full_range,
            "e_invariant": self.e_invariant, "order_tol": self.order_tol, "max_order_zeta": self.max_order_zeta,
            "lock": self.lock,
        }

    def to_dict(self) -> dict[str, Any]:
        """Plain (JSON-able) state; :meth:`from_dict` restores it."""
        return {"params": self.params(), "next_id": self._next_id, "tracks": [tr.to_dict() for tr in self._tracks]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PoleTracker:
        """Rebuild a tracker saved by :meth:`to_dict`."""
        try:
            tracker = cls(**data["params"])
            tracker._next_id = int(data["next_id"])
            tracker._tracks = [Track.from_dict(d) for d in data["tracks"]]
        except (KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"PoleTracker.from_dict: saved state is incomplete or malformed ({err!r})") from err
        return tracker
