"""Sequential change detection on the driveline frequency and damping.

Notes
-----
Input: the driveline estimate at the publish rate (about 10 Hz), its model
uncertainty and the learned baseline of the current speed band
(:class:`~online_id.monitoring.cells.BandStats`).

**Normalised deviation** of each sample (frequency shown; damping alike):

.. math::

    d_f = \\frac{\\operatorname{sign}(f_0 - \\bar f)\\,
          \\max(|f_0 - \\bar f| - \\delta_f \\bar f,\\ 0)}{\\sigma_f}, \\qquad
    \\sigma_f = \\max(s_f, \\sigma_{f,\\text{model}}), \\qquad
    r_f = \\frac{f_0}{\\bar f} - 1

with :math:`\\bar f, s_f` the band's baseline mean and (floored) spread,
:math:`\\sigma_{f,\\text{model}}` the estimator's own uncertainty (a
momentarily poor estimate weighs less) and :math:`\\delta_f` =
``min_change_f`` the smallest relative change worth reporting (a dead band).

**The damping's** :math:`\\sigma_\\zeta = \\max(s_\\zeta,\\ \\sigma_{\\zeta,\\text{model}}
\\min(1, s_\\zeta / \\bar u_\\zeta))`, with :math:`\\bar u_\\zeta` the mean
of the estimator's own damping uncertainty over the baseline's learned
estimates (:attr:`~online_id.monitoring.cells.BandStats.uncertainty_zeta`;
unscaled where it is not known): the estimator's uncertainty calibrated
against the scatter measured where the baseline was learned. On a shaft
with backlash the model's damping uncertainty over-states how much the 1 Hz
estimates scatter, by a factor of 1.7-2.5 (the residual holds the backlash,
which does not change from one window to the next: on two simulated benches
3.0 % of zeta against 1.2 % and 6.8 % against 3.3 %). There a +50 % change, seen as +36 % of which the
dead band leaves 16 %, counted as 2.3 standard deviations instead of 4.8,
and was missed. A momentarily poor estimate still weighs less (the scaling
keeps its ratio to the estimator's usual uncertainty there). The
frequency's uncertainty is not scaled.

**Why a dead band.** The baseline spread is learned over a minute or two;
over hours the apparent resonance of a healthy bench also moves a little
with things the baseline does not see (rubber couplings stiffen with
temperature; the baselines are kept per load, see
:mod:`~online_id.monitoring.baseline`, but within a load cell the load still
moves a little). A CUSUM normalised by the short-term spread alone reports
such shifts as wear. The dead band is the CUSUM's minimum shift of interest
in physical units. The default for the frequency, 0.5 % in :math:`f_0` (1 %
in stiffness), is a compromise measured with ``online-id evaluate``: a 5 %
stiffness loss is 2.5 % in :math:`f_0` on a linear shaft but only about
1.7 % in the apparent resonance of a shaft with a large backlash, and a
wider band misses it there. The default for the damping is 20 %. The
damping of a linear model fitted to a shaft with backlash is not a physical
constant: on the evaluation's benches with the largest gaps the fit settles
at one of two values 30-40 % apart, each for minutes, at the same operating
point (the prediction-error criterion has two nearly equal minima). That is
told apart by the criterion, not by the dead band (it was 40 %, and hid a
+50 % change, estimated at +46 %, even where the damping estimate spread by
only 3 %): before a damping alarm, the confirm refits the window from the
baseline's own solution among other starts and keeps that minimum where its
loss is within ``detection.damping_tie_pct`` (1 %) of the best; the
window then does not contradict the baseline and the alarm is withheld.
The frequency alike (``detection.frequency_tie_pct``, 1 %): the same two
minima differ by 1-3 % in the resonance. Where the data prefer the other
minimum by more (a simulated bench with 0.59 mrad of
backlash: at a learned point the estimate sat 0.9 % above its baseline for
four minutes, where the fit from the baseline's solution lost 1.7 % more
than the best), the service rechecks against the cell's own data: the window
of the cell's first estimates, refitted from the current solution, gives
the current estimate again when only the minimum moved, and the healthy
resonance when the driveline changed
(:mod:`~online_id.estimation.reference`).

**Autocorrelation.**  The estimates come from fits over overlapping windows
(10 s, refitted every second), so neighbouring samples are strongly
correlated and a CUSUM fed at 10 Hz with white-noise thresholds would alarm
constantly.  The deviations are therefore averaged over
intervals of :math:`T` = ``update_interval_s`` and each interval mean is
scaled by the long-run standard deviation of an AR(1) process with
:math:`\\rho = e^{-T/\\tau}` (an effective-sample-size correction):

.. math::

    z_f = \\operatorname{clip}\\left(\\bar d_f \\sqrt{\\frac{1-\\rho}{1+\\rho}},
    \\pm z_{\\max}\\right)

so that a sum of :math:`m \\gg \\tau/T` values of :math:`z` has variance
about :math:`m`, as for white unit noise. A fit over a window of :math:`W`
seconds averages :math:`W/T` intervals, like a moving average whose long-run
variance is :math:`W/T` times the marginal one; the AR(1) with the same
long-run variance has :math:`(1+\\rho)/(1-\\rho) = W/T`
(:func:`correlation_for_window`: :math:`\\tau \\approx` 5 s for 10 s
windows). The clip bounds the effect of a single wild estimate.

**Two-sided CUSUM** per quantity (:math:`k` = ``k``):

.. math::

    S^+_t = \\min(\\max(0, S^+_{t-1} + z_t - k), S_{\\max}), \\qquad
    S^-_t = \\min(\\max(0, S^-_{t-1} - z_t - k), S_{\\max})

A statistic above ``h_warning`` raises a warning, above ``h_fault`` a fault.
:math:`S_{\\max} = 2 h_\\text{fault}` only keeps the numbers bounded.
The change onset is the end of the last interval at which the statistic that
fired was zero; the change is reported as the mean of :math:`r` over the
most recent ``change_window_s`` since the onset (the recent mean follows
the lagging estimator better than the mean since the onset), and for the
frequency also as a stiffness change
:math:`\\Delta c/c = (1 + r_f)^2 - 1` (since :math:`\\omega_0^2 \\propto c_s`).

Defaults: with :math:`k = 0.5`, :math:`h` = 8 / 16, :math:`T` = 1 s and
10 s windows, a mean shift of :math:`\\delta` marginal standard deviations
gives :math:`z \\approx \\delta / 3.2`. The false-alarm rate and the
detection delays on simulated benches come from ``online-id evaluate``
(README).

**Alarm rules** (per kind, "frequency" and "damping"):

* *raise*: when no alarm of that kind is latched, the kind is armed and
  :math:`\\max(S^+, S^-) >` ``h_warning`` (level 1) or ``h_fault`` (level 2);
* *escalate*: a latched warning becomes a fault when the statistic passes
  ``h_fault`` (a new :class:`Alarm` with level 2 is returned); the level never
  drops while latched;
* *latch*: the alarm stays in :attr:`ChangeDetector.active` until
  :meth:`ChangeDetector.acknowledge`; the statistics keep running;
* *acknowledge*: clears the latch and restarts both statistics of every
  acknowledged kind at zero, and its onset and change estimates;
* *hysteresis / re-arm*: after raising, a kind is disarmed; it is re-armed
  only once its statistic is below ``hysteresis * h_warning`` with no alarm
  latched.  Since the acknowledgement restarts the statistic at zero, a
  change still present after the acknowledgement is reported again only if
  it persists long enough to carry the statistic from zero past
  ``h_warning`` (about ``h_warning / (|z| - k)`` intervals); a deviation
  that has gone is not;
* *confirm*: before a new alarm (not an escalation) is raised, the caller's
  ``confirm(kind)`` may look at the data again; if it finds no deviation
  beyond the dead band, the alarm is withheld (counted in
  :attr:`ChangeDetector.withheld`) and the statistic of that kind restarts
  at zero, armed. The service refits the current window from several
  starts, the baseline's own solution among them: with a model that does
  not fit exactly (backlash), the prediction-error criterion has several
  nearly equal minima, and a warm-started fit can stay in one whose
  resonance or damping differs from the baseline's while another start
  fits the same data as well or better. Against a cell's own baseline it
  then refits the data the cell was learned from, from the current
  solution, and withholds the alarm where they give the current estimate
  again (see above);
* *suppression*: while ``suppressed`` is true or ``baseline`` is None the
  sample is ignored: the statistics stay frozen, the current interval is
  discarded and nothing is raised.

When both kinds raise at once, :meth:`ChangeDetector.update` returns one
alarm and the next call returns the other.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import asdict, dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Callable, Mapping

from online_id.monitoring import defaults
from online_id.monitoring.checks import number
from online_id.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from online_id.monitoring.cells import BandStats

FREQUENCY = "frequency"
DAMPING = "damping"
KINDS = (FREQUENCY, DAMPING)


@dataclass(frozen=True)
class Alarm:
    """A detected change of the driveline frequency or damping.

    Attributes
    ----------
    kind
        ``"frequency"`` or ``"damping"``.
    level
        1 warning, 2 fault.
    since_t_s
        Estimated onset of the change (last time the statistic was zero).
    detected_t_s
        When the statistic crossed the level.
    speed_rpm
        Engine speed (mean of the last interval) at detection.
    change_pct
        Relative change of the frequency or damping against the baseline [%].
    stiffness_change_pct
        For the frequency: the implied stiffness change
        :math:`((1 + r)^2 - 1) \\cdot 100` [%]; None for the damping.
    message
        One line for logs and operators.
    """

    kind: str
    level: int
    since_t_s: float
    detected_t_s: float
    speed_rpm: float
    change_pct: float
    stiffness_change_pct: float | None
    message: str

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


EPOCH_AFTER_S = 1e8  # stream times above this are Unix time (SocketCAN, candump logs), below it seconds from a start


def when_text(t_s: float) -> str:
    """A stream time for people: UTC clock time for Unix timestamps, else ``t = ... s``."""
    if t_s > EPOCH_AFTER_S:
        return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t_s))
    return f"t = {t_s:.1f} s"


def alarm_message(kind: str, level: int, change_pct: float, stiff_pct: float | None, since: float, rpm: float,
                  what: str | None = None) -> str:
    """An alarm's line for people: "warning: driveline frequency 2.4 % lower (stiffness about 5 % lower) since
    t = 104.9 s at 2999 rpm"; ``what`` names the quantity (default: the driveline frequency or damping)."""
    word = "lower" if change_pct < 0 else "higher"
    if what is None:
        what = "driveline frequency" if kind == FREQUENCY else "driveline damping"
    text = f"{what} {abs(change_pct):.1f} % {word}"
    if stiff_pct is not None:
        sword = "lower" if stiff_pct < 0 else "higher"
        text += f" (stiffness about {abs(stiff_pct):.0f} % {sword})"
    text += f" since {when_text(since)} at {rpm:.0f} rpm"
    return ("fault: " if level >= 2 else "warning: ") + text


def _num(name: str, value: float, *, low: float = 0.0, strict: bool = True) -> float:
    return number("ChangeDetector", name, value, low=low, strict=strict)


def _dead_band(x: float, width: float) -> float:
    """``x`` moved toward zero by ``width`` (zero inside the band)."""
    return x - width if x > width else x + width if x < -width else 0.0


def correlation_for_window(window_s: float, interval_s: float = 1.0) -> float:
    """AR(1) correlation time with the long-run variance of estimates from windows of ``window_s``."""
    m = max(window_s / interval_s, 1.0 + 1e-9)
    rho = (m - 1.0) / (m + 1.0)
    return -interval_s / math.log(rho) if rho > 0.0 else interval_s


class ChangeDetector:
    """Two-sided CUSUM on the normalised deviations of :math:`f_0` and :math:`\\zeta`.

    See the module notes for the statistic, the defaults and the alarm rules.

    Parameters
    ----------
    k
        Reference value (allowance) of the CUSUM, in long-run standard
        deviations of the interval mean.
    h_warning, h_fault
        Decision levels of warning and fault (``0 < h_warning < h_fault``).
    update_interval_s
        Interval :math:`T` over which the deviations are averaged before one
        CUSUM step.
    hysteresis
        A disarmed kind is re-armed once its statistic is below
        ``hysteresis * h_warning`` (``0 <= hysteresis < 1``).
    correlation_s
        Correlation time :math:`\\tau` of the estimation error; for estimates
        from overlapping windows see :func:`correlation_for_window` (the default,
        5 s, is that of the service's 10 s windows).
    z_clip
        Largest magnitude of one normalised interval mean.
    change_window_s
        The reported change is the mean relative deviation over at most this
        long before detection (and not before the onset).
    min_change_f, min_change_zeta
        Dead bands: relative deviations of the frequency and the damping from
        the baseline below these count as none (see the module notes).
    """

    def __init__(
        self,
        *,
        k: float = defaults.K,
        h_warning: float = defaults.H_WARNING,
        h_fault: float = defaults.H_FAULT,
        update_interval_s: float = 1.0,
        hysteresis: float = 0.5,
        correlation_s: float = 5.0,
        z_clip: float = 5.0,
        change_window_s: float = 5.0,
        min_change_f: float = defaults.MIN_FREQ_CHANGE_PCT / 100.0,
        min_change_zeta: float = defaults.MIN_DAMPING_CHANGE_PCT / 100.0,
    ) -> None:
        self.k = _num("k", k, strict=False)
        self.h_warning = _num("h_warning", h_warning)
        self.h_fault = _num("h_fault", h_fault)
        if self.h_fault <= self.h_warning:
            raise ConfigError(f"ChangeDetector: expected h_fault > h_warning = {h_warning}, but got {h_fault}")
        self.update_interval_s = _num("update_interval_s", update_interval_s)
        self.hysteresis = _num("hysteresis", hysteresis, strict=False)
        if self.hysteresis >= 1.0:
            raise ConfigError(f"ChangeDetector: expected 0 <= hysteresis < 1, but got {hysteresis}")
        self.correlation_s = _num("correlation_s", correlation_s)
        self.z_clip = _num("z_clip", z_clip)
        self.change_window_s = _num("change_window_s", change_window_s)
        self.min_change_f = _num("min_change_f", min_change_f, strict=False)
        self.min_change_zeta = _num("min_change_zeta", min_change_zeta, strict=False)
        rho = math.exp(-self.update_interval_s / self.correlation_s)
        self._scale = math.sqrt((1.0 - rho) / (1.0 + rho))  # 1 / long-run std of the interval mean
        self._s_max = 2.0 * self.h_fault
        self._n_recent = max(1, int(round(self.change_window_s / self.update_interval_s)))
        self._reset_all()

    # -- state -------------------------------------------------------------------------------
    def _reset_all(self) -> None:
        # statistics per kind: [S+, S-]; onset per kind and side; intervals since onset
        self._S = {kind: [0.0, 0.0] for kind in KINDS}
        self._onset: dict[str, list[float | None]] = {kind: [None, None] for kind in KINDS}
        self._n_since = {kind: [0, 0] for kind in KINDS}
        self._recent: dict[str, deque[float]] = {kind: deque(maxlen=self._n_recent) for kind in KINDS}
        self._latched: dict[str, Alarm | None] = {kind: None for kind in KINDS}
        self._armed = {kind: True for kind in KINDS}
        self._pending: list[Alarm] = []
        self.withheld = {kind: 0 for kind in KINDS}  # alarms not confirmed (see module notes)
        self._t_last: float | None = None
        self._clear_interval()

    def _clear_interval(self) -> None:
        self._t_open: float | None = None
        # n, sum d_f, sum d_z, sum r_f, sum r_z, sum rpm, n of the damping (not counted: frequency only)
        self._acc = [0, 0.0, 0.0, 0.0, 0.0, 0.0, 0]

    # -- per sample --------------------------------------------------------------------------
    def update(
        self,
        *,
        t_s: float,
        speed_rpm: float,
        f0_hz: float,
        zeta: float,
        f0_std_hz: float,
        zeta_std: float,
        baseline: BandStats | None,
        suppressed: bool,
        confirm: Callable[[str], bool | None] | None = None,
        frequency_only_beyond: float | None = None,
    ) -> Alarm | None:
        """One estimate in; a new or escalated alarm out (None otherwise).

        Samples with ``suppressed`` true, ``baseline`` None or a non-finite
        frequency or damping are ignored (statistics frozen).  Non-finite
        model uncertainties count as zero (the baseline spread is used).
        ``confirm(kind)`` is asked before a new alarm is raised (see the
        module notes, *confirm*).  ``frequency_only_beyond``: this sample
        counts for the frequency only, with this relative dead band instead
        of ``min_change_f`` (the settle time after a change of operating
        point, when only a large change of the frequency is to be believed);
        the damping's statistics are left as they are.
        """
        alarm = None
        usable = (
            not suppressed
            and baseline is not None
            and math.isfinite(f0_hz)
            and math.isfinite(zeta)
            and math.isfinite(speed_rpm)
        )
        if not usable:
            self._clear_interval()
        else:
            if self._t_open is not None and t_s >= self._t_open + self.update_interval_s * (1.0 - 1e-6):
                self._close_interval(self._t_last if self._t_last is not None else t_s, confirm)
                self._clear_interval()
            if self._t_open is None:
                self._t_open = t_s
            sf = max(baseline.std_f, f0_std_hz if math.isfinite(f0_std_hz) else 0.0)
            sz = max(baseline.std_zeta, self._scatter_zeta(baseline, zeta_std))
            acc = self._acc
            band_f = self.min_change_f if frequency_only_beyond is None else frequency_only_beyond
            acc[0] += 1
            excess = baseline.excess_f(f0_hz)  # f0 - mean, or beyond a bracket's bounds
            acc[1] += _dead_band(excess, band_f * baseline.mean_f) / sf  # d_f
            acc[3] += excess / baseline.mean_f  # r_f
            acc[5] += speed_rpm
            if frequency_only_beyond is None:
                acc[2] += _dead_band(zeta - baseline.mean_zeta, self.min_change_zeta * baseline.mean_zeta) / sz
                acc[4] += zeta / baseline.mean_zeta - 1.0  # r_zeta
                acc[6] += 1
            self._t_last = t_s
        if self._pending:
            alarm = self._pending.pop(0)
        return alarm

    @staticmethod
    def _scatter_zeta(baseline: BandStats, zeta_std: float) -> float:
        """The estimator's own damping uncertainty, scaled down to the scatter measured where the baseline was
        learned (see the module notes); 0 for a non-finite one."""
        if not math.isfinite(zeta_std):
            return 0.0
        u = baseline.uncertainty_zeta
        if math.isfinite(u) and u > 0.0:
            return zeta_std * min(1.0, baseline.std_zeta / u)
        return zeta_std

    def _close_interval(self, t_end: float, confirm: Callable[[str], bool | None] | None) -> None:
        n, sdf, sdz, srf, srz, srpm, nz = self._acc
        if n == 0:
            return
        rpm = srpm / n
        channels = [(FREQUENCY, sdf / n, srf / n)] + ([(DAMPING, sdz / nz, srz / nz)] if nz else [])
        for kind, d_mean, r_mean in channels:
            z = min(max(d_mean * self._scale, -self.z_clip), self.z_clip)
            S = self._S[kind]
            S[0] = min(max(0.0, S[0] + z - self.k), self._s_max)  # S+ = max(0, S+ + z - k)
            S[1] = min(max(0.0, S[1] - z - self.k), self._s_max)  # S- = max(0, S- - z - k)
            self._recent[kind].append(r_mean)
            for side in (0, 1):
                if S[side] == 0.0:
                    self._onset[kind][side] = t_end
                    self._n_since[kind][side] = 0
                else:
                    if self._onset[kind][side] is None:
                        self._onset[kind][side] = self._t_open if self._t_open is not None else t_end
                    self._n_since[kind][side] += 1
            self._decide(kind, t_end, rpm, confirm)

    def _decide(self, kind: str, t_end: float, rpm: float, confirm: Callable[[str], bool | None] | None) -> None:
        S = self._S[kind]
        side = 0 if S[0] >= S[1] else 1
        s = S[side]
        level = 2 if s > self.h_fault else 1 if s > self.h_warning else 0
        latched = self._latched[kind]
        if latched is None and not self._armed[kind] and max(S) < self.hysteresis * self.h_warning:
            self._armed[kind] = True
        if level == 0:
            return
        if latched is None and not self._armed[kind]:
            return
        if latched is not None and level <= latched.level:
            return
        if latched is None and confirm is not None:
            verdict = confirm(kind)
            if verdict is None:
                return  # the check runs elsewhere (a worker): decide at the next interval
            if not verdict:
                self.withheld[kind] += 1
                self._restart(kind)  # the deviation is not in the data: start again from zero, still armed
                return
        n = max(1, min(self._n_since[kind][side], len(self._recent[kind])))
        recent = list(self._recent[kind])[-n:]
        r = sum(recent) / len(recent)
        change = 100.0 * r
        stiff = 100.0 * ((1.0 + r) ** 2 - 1.0) if kind == FREQUENCY else None
        since = self._onset[kind][side]
        since = t_end if since is None else since
        if latched is not None:  # escalation keeps the onset of the latched alarm
            since = latched.since_t_s
        alarm = Alarm(kind, level, float(since), float(t_end), float(rpm), float(change),
                      None if stiff is None else float(stiff), alarm_message(kind, level, change, stiff, since, rpm))
        self._latched[kind] = alarm
        self._armed[kind] = False
        self._pending.append(alarm)

    def latch(self, alarm: Alarm) -> bool:
        """Latch an alarm another test raised (the engaged flank's, :mod:`online_id.monitoring.engaged`), as the
        statistics' own alarms are: unless an alarm of its kind of the same or a higher level is latched.
        Acknowledged with the others; the kind's statistics run on. Returns whether it was latched."""
        if alarm.kind not in KINDS:
            raise ValueError(f"ChangeDetector.latch: expected kind in {KINDS}, but got {alarm.kind!r}")
        latched = self._latched[alarm.kind]
        if latched is not None and alarm.level <= latched.level:
            return False
        self._latched[alarm.kind] = alarm
        self._armed[alarm.kind] = False
        return True

    # -- commands ----------------------------------------------------------------------------
    def acknowledge(self, kind: str | None = None) -> None:
        """Clear the latched alarm(s) and restart their statistics at zero.

        Parameters
        ----------
        kind
            ``"frequency"``, ``"damping"`` or None for both.
        """
        if kind is not None and kind not in KINDS:
            raise ValueError(f"ChangeDetector.acknowledge: expected kind in {KINDS}, but got {kind!r}")
        for kd in KINDS if kind is None else (kind,):
            self._latched[kd] = None
            self._restart(kd)
        self._pending = [a for a in self._pending if self._latched[a.kind] is not None]

    def _restart(self, kind: str) -> None:
        """Statistics of ``kind`` from zero, armed (after an acknowledgement or a withheld alarm)."""
        self._S[kind] = [0.0, 0.0]
        self._onset[kind] = [None, None]
        self._n_since[kind] = [0, 0]
        self._recent[kind].clear()
        self._armed[kind] = True  # statistic is 0 < hysteresis * h_warning

    def new_stream(self) -> None:
        """A new run with its own time base (a restored state, another log): drop the open interval.

        Statistics and latched alarms are kept; only the interval being
        averaged, whose times belong to the previous stream, is discarded.
        """
        self._clear_interval()
        self._t_last = None

    def reset(self) -> None:
        """Forget everything (statistics, latched alarms); for a re-learned baseline."""
        self._reset_all()

    # -- read-only results ---------------------------------------------------------------------
    @property
    def active(self) -> Alarm | None:
        """The latched alarm of highest level (frequency first on equal levels), or None."""
        alarms = self.alarms
        if not alarms:
            return None
        return max(alarms, key=lambda a: (a.level, a.kind == FREQUENCY))

    @property
    def alarms(self) -> tuple[Alarm, ...]:
        """All latched alarms (at most one per kind)."""
        return tuple(a for a in (self._latched[k] for k in KINDS) if a is not None)

    @property
    def statistics(self) -> Mapping[str, float]:
        """Current CUSUM values: ``frequency_up``, ``frequency_down``, ``damping_up``, ``damping_down``."""
        return MappingProxyType({
            "frequency_up": self._S[FREQUENCY][0],
            "frequency_down": self._S[FREQUENCY][1],
            "damping_up": self._S[DAMPING][0],
            "damping_down": self._S[DAMPING][1],
        })

    # -- persistence -----------------------------------------------------------------------------
    def params(self) -> dict[str, float]:
        return {
            "k": self.k, "h_warning": self.h_warning, "h_fault": self.h_fault,
            "update_interval_s": self.update_interval_s, "hysteresis": self.hysteresis,
            "correlation_s": self.correlation_s, "z_clip": self.z_clip, "change_window_s": self.change_window_s,
            "min_change_f": self.min_change_f, "min_change_zeta": self.min_change_zeta,
        }

    def to_dict(self) -> dict[str, Any]:
        """Plain (JSON-able) state; :meth:`from_dict` restores it, latched alarms included."""
        return {
            "params": self.params(),
            "S": {k: list(v) for k, v in self._S.items()},
            "onset": {k: list(v) for k, v in self._onset.items()},
            "n_since": {k: list(v) for k, v in self._n_since.items()},
            "recent": {k: list(v) for k, v in self._recent.items()},
            "latched": {k: (None if a is None else a.as_dict()) for k, a in self._latched.items()},
            "armed": dict(self._armed),
            "pending": [a.as_dict() for a in self._pending],
            "withheld": dict(self.withheld),
            "t_open": self._t_open,
            "t_last": self._t_last,
            "acc": list(self._acc),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ChangeDetector:
        """Rebuild a detector saved by :meth:`to_dict`."""
        try:
            det = cls(**data["params"])
            det._S = {k: [float(x) for x in data["S"][k]] for k in KINDS}
            det._onset = {k: [None if x is None else float(x) for x in data["onset"][k]] for k in KINDS}
            det._n_since = {k: [int(x) for x in data["n_since"][k]] for k in KINDS}
            det._recent = {k: deque((float(x) for x in data["recent"][k]), maxlen=det._n_recent) for k in KINDS}
            det._latched = {k: (None if a is None else Alarm(**a)) for k, a in data["latched"].items()}
            det._armed = {k: bool(data["armed"][k]) for k in KINDS}
            det._pending = [Alarm(**a) for a in data.get("pending", [])]
            det.withheld = {k: int(data.get("withheld", {}).get(k, 0)) for k in KINDS}
            det._t_open = data.get("t_open")
            det._t_last = data.get("t_last")
            acc = list(data.get("acc", [0, 0.0, 0.0, 0.0, 0.0, 0.0, 0]))
            if len(acc) == 6:  # saved before the damping had its own count: every sample counted for both
                acc.append(acc[0])
            det._acc = [int(acc[0])] + [float(x) for x in acc[1:6]] + [int(acc[6])]
        except (KeyError, TypeError) as err:
            raise ConfigError(f"ChangeDetector.from_dict: saved state is incomplete or malformed ({err!r})") from err
        return det
