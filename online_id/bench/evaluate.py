"""Evaluation of wear and fault detection on simulated benches (no I/O; the CLI prints and plots).

Two kinds of run, each a simulated bench fed sample by sample through the
service pipeline (:func:`~online_id.service.pipeline.run_bench_data`: the same
assembler, estimator, baselines and detector as the live service):

* **fault-free hours** -- a random plant (resonance 16-34 Hz, damping ratio
  3-8 %, 4 or 6 cylinders), random measurement noise, temperature-like
  friction drift, a random subset of effects the model does not declare
  (torque ripple at an engine order, a fixed-frequency disturbance, a sensor
  delay, backlash, a structural resonance), and 3-4 operating points visited
  in turn for 3-7 minutes each with a few rpm of jitter, for an hour. Every
  drift alarm is a false alarm; an operator acknowledges it 30 s later, so
  later alarms count too;
* **faults** -- a random plant as above at one operating point; after the
  baseline has been learned (about 100 s), at a random time, the shaft
  stiffness drops by 5, 10 or 20 % or the shaft damping changes by +-50 %.
  The detection delay is the time from the fault to the first alarm of the
  expected kind (warning, and separately fault level).

Scenario families of how benches run (``family``; the fault cases of
``FAMILY_CASES``):

* **(a) first run** -- a fresh service (nothing learned); 2-4 operating
  points of 30-60 s visited in turn; the fault after 60-120 s of data;
* **(b) later run** -- the state of an earlier healthy run (120-180 s at 2-3
  operating points) carried into a run at other operating points (pooled
  baselines serve them), the fault 30-90 s into it; a drift alarm of the
  earlier run is a false alarm of the run too (acknowledged after 30 s, so
  the state carried on holds none latched);
* **(c) long runs** -- the dwell at one operating point above.

Fault-free hours come in two kinds alternating: the long dwells above, and
short plateaus (operating points changing every 30-60 s).

The test torque is the seed paper's excitation: a maximal-length PRBS of
30-50 Nm with a 1 s period.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from online_id.bench.scenario import (
    Backlash,
    BenchScenario,
    Effects,
    Fault,
    Friction,
    Noise,
    OperatingPoint,
    PrbsSettings,
    SensorDelay,
    SinusoidalDisturbance,
    StructuralResonance,
    TorqueRipple,
)
from online_id.bench.simulate import simulate_bench
from online_id.config import ModelSettings, Settings
from online_id.service.pipeline import COMMAND_ACK, Pipeline, run_bench_data
from online_id.records import AlertKind, AlertOut, EstimateOut

DRIFT_KINDS = (AlertKind.FREQ_DRIFT, AlertKind.DAMPING_DRIFT)
FAULT_CASES = (  # (label, stiffness factor, damping factor, expected alarm)
    ("stiffness -5 %", 0.95, 1.0, AlertKind.FREQ_DRIFT),
    ("stiffness -10 %", 0.90, 1.0, AlertKind.FREQ_DRIFT),
    ("stiffness -20 %", 0.80, 1.0, AlertKind.FREQ_DRIFT),
    ("damping +50 %", 1.0, 1.5, AlertKind.DAMPING_DRIFT),
    ("damping -50 %", 1.0, 0.5, AlertKind.DAMPING_DRIFT),
)
FAMILY_CASES = (  # the fault cases of families (a) and (b)
    ("stiffness -5 %", 0.95, 1.0, AlertKind.FREQ_DRIFT),
    ("stiffness -10 %", 0.90, 1.0, AlertKind.FREQ_DRIFT),
    ("stiffness -15 %", 0.85, 1.0, AlertKind.FREQ_DRIFT),
    ("damping +50 %", 1.0, 1.5, AlertKind.DAMPING_DRIFT),
    ("damping -50 %", 1.0, 0.5, AlertKind.DAMPING_DRIFT),
)
FAMILIES = ("a", "b", "c")
ACK_AFTER_S = 30.0
SPEEDS_RPM = tuple(range(1000, 3001, 250))


@dataclass(frozen=True)
class Crossing:
    """An operating point where engine order ``order`` sits at ``ratio`` times the resonance (within 25 %)."""

    speed_rpm: float
    order: float
    ratio: float  # order line [Hz] / resonance [Hz]


@dataclass(frozen=True)
class BenchRealism:
    """What a bench adds to perfect samples (run by ``online_id.offline.bench_feed``).

    ``frame_loss``: the fraction of input frames dropped at random; ``jitter_s``: each frame is received up to
    this much late (uniform), in order (a receive queue); ``worker_lag_s``: the slow work (window refits,
    checks, physical fits, the backlash test) is adopted this many stream seconds after it was submitted, as
    the live service's worker process hands it back.
    """

    frame_loss: float = 0.0
    jitter_s: float = 0.0
    worker_lag_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.frame_loss < 1.0:
            raise ValueError(f"BenchRealism: expected frame_loss in [0, 1), but got {self.frame_loss!r}")
        for name in ("jitter_s", "worker_lag_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"BenchRealism: expected {name} >= 0, but got {v!r}")


BENCH_REALISM = BenchRealism(frame_loss=0.01, jitter_s=0.002, worker_lag_s=0.5)
"""``--bench-realism``: 1 % of the frames lost, up to 2 ms of receive jitter (twice the frame period), and
slow work adopted 0.5 s after submission."""


@dataclass(frozen=True)
class RunSpec:
    """One evaluation run: a scenario and what it should (not) raise."""

    case: str  # "fault-free" or a FAULT_CASES label
    seed: int
    scenario: BenchScenario
    t_fault_s: float | None = None
    expect: AlertKind | None = None
    family: str = "c"  # "a", "b", "c" (see module notes); fault-free: "long" or "short"
    earlier: BenchScenario | None = None  # (b): the healthy run whose state this run starts from
    crossings: tuple[Crossing, ...] = ()  # operating points of the run where an order line crosses the resonance
    realism: BenchRealism | None = None  # frames with loss and jitter, the worker's lag (None: perfect samples)


@dataclass
class RunResult:
    """What one run gave."""

    case: str
    seed: int
    duration_s: float
    f0_hz: float
    zeta: float
    effects: list[str]
    alarms: list[dict[str, Any]] = field(default_factory=list)  # every new drift alarm
    t_fault_s: float | None = None
    warning_delay_s: float | None = None  # first alarm of the expected kind after the fault
    fault_delay_s: float | None = None  # first fault-level alarm of the expected kind
    false_alarms: int = 0  # drift alarms before the fault (all in a fault-free run; (b): the earlier run's too)
    valid_fraction: float = 0.0
    f0_err_pct: list[float] = field(default_factory=list)  # valid estimates vs truth, 1 Hz, before any fault
    elapsed_s: float = 0.0
    family: str = "c"
    cells: list[dict[str, Any]] = field(default_factory=list)  # the baseline cells at the end
    zeta_trace: list[list[float]] = field(default_factory=list)  # [t_s, zeta] of the valid estimates, 1 Hz (fault runs)
    # alarms the detector asked for and the confirm withheld (second look, recheck), per kind, in this run before
    # the fault (all of a fault-free run) and after it: how often the guards stood between the bench and an alarm
    withheld_before_fault: dict[str, int] = field(default_factory=dict)
    withheld_after_fault: dict[str, int] = field(default_factory=dict)
    wrong_kind_alarms: int = 0  # drift alarms after the fault of the other kind than the fault's
    wrong_kind_delay_s: float | None = None  # the first of them, from the fault
    # each visit of an operating point where an engine-order line crosses the resonance (split at the fault):
    # speed, order, line/resonance ratio, times, estimates published and valid, alarms, outcome (see run)
    crossings: list[dict[str, Any]] = field(default_factory=list)
    realism: dict[str, float] | None = None  # the BenchRealism of the run (None: perfect samples)

    def zeta_summary(self) -> dict[str, float | None]:
        """Spread of the healthy damping estimates (after 40 s, before any fault) and the change they show
        from 15 s after the fault on, both relative to the healthy mean [%] (None where there are none)."""
        z = np.asarray(self.zeta_trace, dtype=float).reshape(-1, 2)
        t_fault = np.inf if self.t_fault_s is None else self.t_fault_s
        pre = z[(z[:, 0] > 40.0) & (z[:, 0] < t_fault), 1]
        post = z[z[:, 0] > t_fault + 15.0, 1]
        mean = float(np.mean(pre)) if pre.size > 1 else None
        return {"spread_pct": 100.0 * float(np.std(pre)) / mean if mean else None,
                "change_pct": 100.0 * (float(np.mean(post)) / mean - 1.0) if mean and post.size else None}

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def random_driveline(rng: np.random.Generator, f0_hz: tuple[float, float] = (16.0, 34.0),
                     zeta: tuple[float, float] = (0.03, 0.08)) -> tuple[dict[str, Any], float]:
    """Scenario fields ``J1, J2, c_s, d_s, n_cyl, noise`` of a random two-mass driveline (inertias 0.5-1.2 and
    0.2-0.6 kg m^2, resonance and damping ratio uniform in ``f0_hz`` and ``zeta``, 4 or 6 cylinders,
    measurement noise), and its resonance [Hz] as drawn."""
    J1 = rng.uniform(0.5, 1.2)
    J2 = rng.uniform(0.2, 0.6)
    f0 = rng.uniform(*f0_hz)
    z = rng.uniform(*zeta)
    J = J1 * J2 / (J1 + J2)
    c_s = (2.0 * math.pi * f0) ** 2 * J
    d_s = 2.0 * z * math.sqrt(c_s * J)
    n_cyl = int(rng.choice([4, 6]))
    noise = Noise(dyno_speed_rpm=rng.uniform(0.02, 0.1), engine_speed_rpm=rng.uniform(0.05, 0.2),
                  torque_nm=rng.uniform(0.1, 0.5))
    return {"J1": J1, "J2": J2, "c_s": c_s, "d_s": d_s, "n_cyl": n_cyl, "noise": noise}, f0


def random_plant(rng: np.random.Generator) -> dict[str, Any]:
    """Scenario fields of a random bench (see module notes)."""
    plant, f0 = random_driveline(rng)
    friction = Friction(b0=rng.uniform(3.0, 8.0), b1=rng.uniform(0.01, 0.03), b2=2e-5,
                        drift=rng.uniform(-0.4, 0.2), drift_tau_s=rng.uniform(300.0, 1800.0))
    fx: dict[str, Any] = {}
    if rng.random() < 0.4:
        fx["torque_ripple"] = TorqueRipple(order=float(rng.choice([1.0, 3.0])), amplitude_nm=rng.uniform(1.0, 4.0))
    if rng.random() < 0.4:
        fx["disturbance"] = SinusoidalDisturbance(freq_hz=rng.uniform(1.6, 3.0) * f0,
                                                  amplitude_nm=rng.uniform(0.5, 2.0))
    if rng.random() < 0.3:
        fx["sensor_delay"] = SensorDelay(signal=str(rng.choice(["dyno_speed", "dyno_torque"])),
                                         delay_s=float(rng.choice([0.001, 0.002])))
    if rng.random() < 0.3:
        fx["backlash"] = Backlash(gap_rad=rng.uniform(0.0005, 0.002))
    if rng.random() < 0.2:
        fx["structural_resonance"] = StructuralResonance(freq_hz=rng.uniform(2.5, 4.0) * f0, zeta=0.02,
                                                         amplitude_nm=rng.uniform(0.2, 1.0))
    return {
        **plant, "friction": friction, "effects": Effects(**fx),
        "prbs": PrbsSettings(amplitude_nm=rng.uniform(30.0, 50.0), period_s=1.0),
    }


def resonance_hz(plant: dict[str, Any]) -> float:
    """The undamped resonance [Hz] of the two-mass driveline of scenario fields ``plant``."""
    J = plant["J1"] * plant["J2"] / (plant["J1"] + plant["J2"])
    return math.sqrt(plant["c_s"] / J) / (2.0 * math.pi)


def engine_orders(plant: dict[str, Any], multiples: int = 1) -> list[float]:
    """The engine orders of the plant's torque: the firing order ``n_cyl / 2`` and its first ``multiples``
    multiples (the compression pulses carry them), and the order of a torque ripple."""
    orders = [plant["n_cyl"] / 2.0 * k for k in range(1, multiples + 1)]
    if plant["effects"].torque_ripple is not None:
        orders.append(plant["effects"].torque_ripple.order)
    return orders


def usable_speeds(plant: dict[str, Any]) -> list[float]:
    """Speeds whose engine-order lines stay at least 25 % away from the resonance."""
    f0 = resonance_hz(plant)
    orders = engine_orders(plant)
    return [float(s) for s in SPEEDS_RPM if all(abs(o * s / 60.0 - f0) > 0.25 * f0 for o in orders)]


CROSSING_NEAR = 0.25  # an order line within this fraction of the resonance crosses it
CROSSING_RPM = (400.0, 3000.0)  # the speeds a crossing point is drawn from
CROSSING_MULTIPLES = 3  # the firing order and its multiples up to the third


def crossing_at(plant: dict[str, Any], speed_rpm: float) -> Crossing | None:
    """The engine order whose line at ``speed_rpm`` lies nearest the resonance, if within ``CROSSING_NEAR``."""
    f0 = resonance_hz(plant)
    near = [(abs(o * speed_rpm / 60.0 / f0 - 1.0), o) for o in engine_orders(plant, CROSSING_MULTIPLES)]
    gap, order = min(near)
    return Crossing(float(speed_rpm), order, order * speed_rpm / 60.0 / f0) if gap <= CROSSING_NEAR else None


def draw_crossing(plant: dict[str, Any], rng: np.random.Generator, within: float = 0.2) -> Crossing | None:
    """An operating point in ``CROSSING_RPM`` where one of the plant's engine orders (drawn among those that
    can) lies within ``within`` of the resonance (uniform in that band); None if no order can."""
    f0 = resonance_hz(plant)
    options = []
    for o in engine_orders(plant, CROSSING_MULTIPLES):
        lo = max(-within, CROSSING_RPM[0] * o / 60.0 / f0 - 1.0)
        hi = min(within, CROSSING_RPM[1] * o / 60.0 / f0 - 1.0)
        if lo < hi:
            options.append((o, lo, hi))
    if not options:
        return None
    o, lo, hi = options[int(rng.integers(len(options)))]
    ratio = 1.0 + float(rng.uniform(lo, hi))
    return Crossing(round(60.0 * f0 * ratio / o, 1), o, ratio)


def fault_free_spec(seed: int, duration_s: float = 3600.0, short: bool = False, crossing: bool = False) -> RunSpec:
    """A fault-free run of ``duration_s`` with 3-4 operating points visited in turn (``short``: 30-60 s each);
    ``crossing``: one more point where an engine-order line crosses the resonance (:func:`draw_crossing`)."""
    rng = np.random.default_rng([seed, 0])
    plant = random_plant(rng)
    speeds = usable_speeds(plant)
    chosen = list(rng.choice(speeds, size=min(len(speeds), int(rng.integers(3, 5))), replace=False))
    cross = _crossings(plant, seed, crossing)
    chosen += [c.speed_rpm for c in cross]
    points: list[OperatingPoint] = []
    t = 0.0
    dwell = (30.0, 60.0) if short else (180.0, 420.0)
    while t < duration_s:
        for s in rng.permutation(chosen):
            d = min(float(rng.uniform(*dwell)), max(duration_s - t, 30.0))
            points.append(OperatingPoint(float(s) + float(rng.uniform(-15.0, 15.0)), d))
            t += d + 3.0
            if t >= duration_s:
                break
    sc = dataclasses.replace(BenchScenario(), seed=seed, operating_points=tuple(points), **plant)
    return RunSpec("fault-free", seed, sc, family="short" if short else "long", crossings=cross)


def _second(speeds: list[float], extra: list[float]) -> list[float]:
    """``speeds`` with ``extra`` visited second (a tour of a few points reaches it whatever its length)."""
    return speeds[:1] + extra + speeds[1:]


def _crossings(plant: dict[str, Any], seed: int, wanted: bool) -> tuple[Crossing, ...]:
    """The crossing point of a run, drawn from a generator of its own (the run's other draws stay as they are)."""
    if not wanted:
        return ()
    c = draw_crossing(plant, np.random.default_rng([seed, 4]))
    return () if c is None else (c,)


def _tour(rng: np.random.Generator, speeds: list[float], until_s: float) -> tuple[OperatingPoint, ...]:
    """Operating points of 30-60 s visited in turn (a few rpm of jitter) until ``until_s``."""
    points: list[OperatingPoint] = []
    t = 0.0
    while t < until_s:
        d = float(rng.uniform(30.0, 60.0))
        points.append(OperatingPoint(speeds[len(points) % len(speeds)] + float(rng.uniform(-15.0, 15.0)), d))
        t += d + BenchScenario().ramp_s
    return tuple(points)


def family_spec(seed: int, case: str, family: str, crossing: bool = False) -> RunSpec:
    """A run of family ``"a"`` or ``"b"`` with one fault of ``case`` (a label of FAMILY_CASES); ``crossing``:
    the run's tour takes in a point where an engine-order line crosses the resonance (:func:`draw_crossing`)."""
    label, k_c, k_d, expect = next(c for c in FAMILY_CASES if c[0] == case)
    rng = np.random.default_rng([seed, 2 if family == "a" else 3])
    plant = random_plant(rng)
    speeds = [float(x) for x in rng.permutation(usable_speeds(plant))]
    fault = lambda t: (Fault(t, stiffness_factor=k_c, damping_factor=k_d),)  # noqa: E731
    cross = _crossings(plant, seed, crossing)
    extra = [c.speed_rpm for c in cross]
    if family == "a":
        n = min(len(speeds), int(rng.integers(2, 5)))
        t_fault = float(rng.uniform(60.0, 120.0))
        sc = dataclasses.replace(BenchScenario(), seed=seed,
                                 operating_points=_tour(rng, _second(speeds[:n], extra), t_fault + 75.0),
                                 faults=fault(t_fault), **plant)
        return RunSpec(label, seed, sc, t_fault, expect, family="a", crossings=cross)
    n = min(len(speeds) // 2, int(rng.integers(2, 4)))
    earlier = dataclasses.replace(BenchScenario(), seed=seed + 7919,
                                  operating_points=_tour(rng, speeds[:n], float(rng.uniform(120.0, 180.0))), **plant)
    later = speeds[n:] or speeds[:n]
    t_fault = float(rng.uniform(30.0, 90.0))
    points = _tour(rng, _second(later[:3], extra), t_fault + 75.0)
    sc = dataclasses.replace(BenchScenario(), seed=seed, operating_points=points, faults=fault(t_fault), **plant)
    return RunSpec(label, seed, sc, t_fault, expect, family="b", earlier=earlier, crossings=cross)


def fault_spec(seed: int, case: str) -> RunSpec:
    """A run with one fault of ``case`` (a label of FAULT_CASES) after the baseline is learned."""
    label, k_c, k_d, expect = next(c for c in FAULT_CASES if c[0] == case)
    rng = np.random.default_rng([seed, 1])
    plant = random_plant(rng)
    speed = float(rng.choice(usable_speeds(plant)))
    t_fault = float(rng.uniform(110.0, 140.0))
    sc = dataclasses.replace(BenchScenario(), seed=seed, operating_points=(OperatingPoint(speed, t_fault + 90.0),),
                             faults=(Fault(t_fault, stiffness_factor=k_c, damping_factor=k_d),), **plant)
    return RunSpec(label, seed, sc, t_fault, expect)


def plan(hours: float, fault_plants: int, seed: int = 1, families: tuple[str, ...] = ("c",),
         cases: tuple[str, ...] | None = None, plant_type: str = "any", crossings: bool = False,
         realism: BenchRealism | None = None) -> list[RunSpec]:
    """Fault-free runs of up to an hour each, making ``hours`` in total (long dwells and short plateaus
    alternating when families (a) or (b) are asked for), and each fault case of each family on each plant.

    ``cases``: only the fault cases with these labels (default: all). ``plant_type``: ``"any"``, or only
    fault plants ``"backlash"`` or ``"no backlash"`` (the first ``fault_plants`` random plants of that type
    in each family; about 30 % of them have backlash). ``crossings``: every fault-free run and every run of
    families (a) and (b) also visits a point where an engine-order line crosses the resonance (the plants
    are those of the same seed without). ``realism``: frames, loss, jitter and the worker's lag of every run.
    """
    runs = []
    left = hours * 3600.0
    k = 0
    short = any(f in families for f in ("a", "b"))
    while left > 1.0:
        runs.append(fault_free_spec(seed * 1000 + k, min(3600.0, left), short=short and k % 2 == 0,
                                    crossing=crossings))
        left -= 3600.0
        k += 1
    if plant_type not in ("any",) + PLANT_TYPES:
        raise ValueError(f"plan: expected plant_type in any, {', '.join(PLANT_TYPES)}, but got {plant_type!r}")

    def of_type(spec: RunSpec) -> bool:
        return plant_type == "any" or (spec.scenario.effects.backlash is not None) == (plant_type == "backlash")

    for family in ("c", "a", "b"):
        if family not in families:
            continue
        table = FAULT_CASES if family == "c" else FAMILY_CASES
        labels = [c[0] for c in table if cases is None or c[0] in cases]
        make = ((lambda p, c: fault_spec(seed * 1000 + 500 + p, c)) if family == "c" else
                (lambda p, c, f=family: family_spec(seed * 1000 + 700 + p, c, f, crossings)))
        p = found = 0
        while found < fault_plants and labels and p < 200 * max(fault_plants, 1):
            if of_type(make(p, labels[0])):  # the plant is the same for every case of a family
                runs.extend(make(p, c) for c in labels)
                found += 1
            p += 1
    if realism is not None:
        runs = [dataclasses.replace(r, realism=realism) for r in runs]
    return runs


def settings_for(spec: RunSpec) -> Settings:
    """The service settings of a run: defaults, with the engine's pulses per revolution."""
    return Settings(model=ModelSettings(pulses_per_rev=spec.scenario.n_cyl / 2.0))


Feed = Callable[..., Pipeline]
"""``feed(data, settings, on_output=..., state=..., run_label=...) -> Pipeline``: bench data through the
service pipeline (:func:`~online_id.service.pipeline.run_bench_data`, or the frame path of
``online_id.offline.bench_feed``)."""


def run(spec: RunSpec, settings: Settings | None = None, feed: Feed | None = None) -> RunResult:
    """Simulate one run and feed it through the pipeline (see module notes); ``feed``: how (default: the
    samples as they are, slow work inline)."""
    t0 = time.monotonic()
    feed = feed or run_bench_data
    rec = simulate_bench(spec.scenario)
    data = rec.to_data(f"evaluation {spec.case} seed {spec.seed}")
    truth = rec.truth
    res = RunResult(spec.case, spec.seed, float(rec.time_s[-1]), truth["f0_hz"], truth["zeta"],
                    [k for k, v in truth["effects"].items() if v is not None], t_fault_s=spec.t_fault_s,
                    realism=None if spec.realism is None else dataclasses.asdict(spec.realism))
    visits = crossing_visits(spec)
    operator = _Operator()
    n_pub = [0, 0]
    next_err = [0.0]
    withheld: dict[str, dict[str, int] | None] = {"start": None, "fault": None}

    def on_output(pipe: Pipeline, t_s: float, out: list) -> None:
        if withheld["start"] is None:  # (b): the earlier run's count comes with its state
            withheld["start"] = dict(pipe.detector.withheld)
        if withheld["fault"] is None and spec.t_fault_s is not None and t_s >= spec.t_fault_s:
            withheld["fault"] = dict(pipe.detector.withheld)
        for a in operator.new_drift_alarms(pipe):
            res.alarms.append(_alarm_record(a))
            visit = _visit_of(visits, a.t_s, with_ramp=True)
            if visit is not None:
                visit["alarms"].append({"t_s": a.t_s, "kind": a.kind.name, "severity": a.severity})
            if spec.t_fault_s is None or a.t_s < spec.t_fault_s:
                res.false_alarms += 1
            elif a.kind == spec.expect:
                delay = a.t_s - spec.t_fault_s
                if res.warning_delay_s is None:
                    res.warning_delay_s = delay
                if a.severity >= 2 and res.fault_delay_s is None:
                    res.fault_delay_s = delay
            else:
                res.wrong_kind_alarms += 1
                if res.wrong_kind_delay_s is None:
                    res.wrong_kind_delay_s = a.t_s - spec.t_fault_s
        est = pipe.last_estimate
        if est is not None and any(isinstance(o, EstimateOut) for o in out):
            n_pub[0] += 1
            n_pub[1] += int(est.valid)
            visit = _visit_of(visits, t_s)
            if visit is not None:
                visit["estimates"] += 1
                visit["valid"] += int(est.valid)
            if est.valid and t_s >= next_err[0]:
                next_err[0] = t_s + 1.0
                if spec.t_fault_s is not None:  # fault runs only: an hour of them would fill results.json
                    res.zeta_trace.append([round(t_s, 1), round(est.zeta, 5)])
                if spec.t_fault_s is None or t_s < spec.t_fault_s:
                    res.f0_err_pct.append(round(100.0 * (est.f0_hz / res.f0_hz - 1.0), 4))
        if spec.t_fault_s is None:  # a false alarm is acknowledged after a while (a fault run is left latched)
            operator.acknowledge_if_due(pipe, t_s)

    settings = settings or settings_for(spec)
    state = None
    if spec.earlier is not None:  # family (b): the state of an earlier healthy run
        earlier = simulate_bench(spec.earlier).to_data(f"evaluation earlier run seed {spec.seed}")
        state = feed(earlier, settings, on_output=_earlier_alarms(res), run_label="earlier run").get_state()
    pipe = feed(data, settings, on_output=on_output, state=state, run_label="this run")
    res.crossings = [dict(v, outcome=_outcome(v, spec, res.alarms)) for v in visits]
    res.family = spec.family
    res.cells = [b.as_dict() for b in pipe.baseline.bands]
    end = dict(pipe.detector.withheld)
    start, at_fault = withheld["start"] or {}, withheld["fault"] or end
    res.withheld_before_fault = {k: max(at_fault.get(k, 0) - start.get(k, 0), 0) for k in end}
    res.withheld_after_fault = {k: max(end[k] - at_fault.get(k, 0), 0) for k in end}
    res.valid_fraction = n_pub[1] / n_pub[0] if n_pub[0] else 0.0
    res.elapsed_s = time.monotonic() - t0
    return res


def crossing_visits(spec: RunSpec) -> list[dict[str, Any]]:
    """The visits of the run's operating points where an engine-order line crosses the resonance
    (:func:`crossing_at`), as records to fill: a visit that spans the fault is split there."""
    sc = spec.scenario
    plant = {"J1": sc.J1, "J2": sc.J2, "c_s": sc.c_s, "n_cyl": sc.n_cyl, "effects": sc.effects}
    out: list[dict[str, Any]] = []
    start = 0.0
    for i, point in enumerate(sc.operating_points):
        if i > 0:
            start += sc.ramp_s
        end = start + point.duration_s
        c = crossing_at(plant, point.speed_rpm)
        if c is not None:
            cuts = [start, end]
            if spec.t_fault_s is not None and start < spec.t_fault_s < end:
                cuts.insert(1, spec.t_fault_s)
            for a, b in zip(cuts[:-1], cuts[1:]):
                out.append({"speed_rpm": round(point.speed_rpm, 1), "order": c.order, "ratio": round(c.ratio, 4),
                            "t_start_s": round(a, 3), "t_end_s": round(b, 3), "ramp_s": sc.ramp_s,
                            "after_fault": spec.t_fault_s is not None and a >= spec.t_fault_s,
                            "estimates": 0, "valid": 0, "alarms": []})
        start = end
    return out


def _visit_of(visits: list[dict[str, Any]], t_s: float, with_ramp: bool = False) -> dict[str, Any] | None:
    """The crossing visit at ``t_s`` (``with_ramp``: the ramp after it counts to it: an alarm on its estimates
    comes a little later)."""
    i = bisect.bisect_right([v["t_start_s"] for v in visits], t_s) - 1
    if i < 0:
        return None
    v = visits[i]
    last = i + 1 == len(visits) or visits[i + 1]["t_start_s"] > v["t_end_s"]  # not split at the fault
    return v if t_s < v["t_end_s"] + (v["ramp_s"] if with_ramp and last else 0.0) else None


CROSSING_OUTCOMES = ("held", "tracked", "false alarm", "warned", "detected", "wrong kind", "latched")
"""What the service did at a crossing visit: before a fault (or in a fault-free run) *held* (its estimate
valid less than half the visit, no alarm), *tracked* (valid, no alarm) or *false alarm*; after the fault
*detected* (a fault-level alarm of the fault's kind raised in the visit), *warned* (a warning of that kind),
*wrong kind* (only an alarm of the other kind), *latched* (no new alarm, one of the fault's kind raised
before the visit), else *held* or *tracked* (no alarm, the fault not yet found)."""


def _outcome(visit: dict[str, Any], spec: RunSpec, alarms_of_run: list[dict[str, Any]]) -> str:
    alarms = visit["alarms"]
    expect = None if spec.expect is None else spec.expect.name
    if not visit["after_fault"]:
        if alarms:
            return "false alarm"
    else:
        mine = [a for a in alarms if a["kind"] == expect]
        if mine:
            return "detected" if any(a["severity"] >= 2 for a in mine) else "warned"
        if alarms:
            return "wrong kind"
        if any(a["kind"] == expect and spec.t_fault_s <= a["t_s"] < visit["t_start_s"] and not a.get("earlier")
               for a in alarms_of_run):
            return "latched"
    return "held" if visit["valid"] < 0.5 * max(visit["estimates"], 1) else "tracked"


class _Operator:
    """The bench operator of a run: reads the pipeline's new drift alarms, and acknowledges a latched one
    ``ACK_AFTER_S`` after the first alarm since the last acknowledgement."""

    def __init__(self) -> None:
        self.seen = 0  # pipeline.alerts_total when last read
        self.open_since: float | None = None

    def new_drift_alarms(self, pipe: Pipeline) -> list[AlertOut]:
        new = pipe.alerts_total - self.seen
        self.seen = pipe.alerts_total
        alarms = [a for a in (pipe.alerts[len(pipe.alerts) - new:] if new else ()) if a.kind in DRIFT_KINDS]
        if alarms and self.open_since is None:
            self.open_since = alarms[0].t_s
        return alarms

    def acknowledge_if_due(self, pipe: Pipeline, t_s: float) -> None:
        if self.open_since is not None and pipe.detector.active is not None and t_s - self.open_since >= ACK_AFTER_S:
            pipe.on_command(COMMAND_ACK, t_s)
            self.open_since = None


def _alarm_record(a: AlertOut, **extra: Any) -> dict[str, Any]:
    return {"t_s": a.t_s, "kind": a.kind.name, "severity": a.severity, "message": a.message, **extra}


def _earlier_alarms(res: RunResult) -> Callable[[Pipeline, float, list], None]:
    """``on_output`` of the earlier healthy run of family (b): every drift alarm it raises is a false alarm
    of the run (``"earlier": True``), acknowledged after ``ACK_AFTER_S`` as an operator would, so the state
    handed on carries no alarm latched."""
    operator = _Operator()

    def on_output(pipe: Pipeline, t_s: float, out: list) -> None:
        for a in operator.new_drift_alarms(pipe):
            res.alarms.append(_alarm_record(a, earlier=True))
            res.false_alarms += 1
        operator.acknowledge_if_due(pipe, t_s)

    return on_output


def summarize(results: list[RunResult]) -> dict[str, Any]:
    """False alarms per hour and detection delays per case (median, worst, missed)."""
    free = [r for r in results if r.case == "fault-free"]
    hours = sum(r.duration_s for r in free) / 3600.0
    n_false = sum(r.false_alarms for r in free)
    n_false_fault = sum(1 for r in free for a in r.alarms if a["severity"] >= 2)
    # backlash with a torque reversing shaft lowers the apparent resonance: no linear truth to compare with
    errs = np.array([e for r in free if "backlash" not in r.effects for e in r.f0_err_pct])
    out: dict[str, Any] = {
        "fault_free": {
            "hours": hours, "runs": len(free), "false_alarms": n_false, "false_fault_alarms": n_false_fault,
            "false_alarms_per_hour": n_false / hours if hours else None,
            **rate_per_1000h(n_false, hours),
            "valid_fraction": float(np.mean([r.valid_fraction for r in free])) if free else None,
            "f0_error_pct_p50_abs": float(np.median(np.abs(errs))) if errs.size else None,
            "f0_error_pct_p99_abs": float(np.quantile(np.abs(errs), 0.99)) if errs.size else None,
            "withheld": _withheld(free, "withheld_before_fault"),
        },
        "faults": [],
    }
    # false alarms by undeclared effect present in the run (an alarm can count under several effects)
    by_effect = {}
    for name in ("none", "backlash", "torque_ripple", "disturbance", "sensor_delay", "structural_resonance"):
        rs = [r for r in free if (name in r.effects if name != "none" else not r.effects)]
        if rs:
            by_effect[name] = {"hours": sum(r.duration_s for r in rs) / 3600.0,
                               "false_alarms": sum(r.false_alarms for r in rs)}
    out["fault_free"]["by_effect"] = by_effect
    out["fault_free"]["by_dwell"] = {
        kind: {"hours": sum(r.duration_s for r in rs) / 3600.0, "false_alarms": sum(r.false_alarms for r in rs)}
        for kind in ("long", "short") if (rs := [r for r in free if r.family == kind])}
    groups = [(fam, label) for fam in FAMILIES
              for label, *_ in (FAULT_CASES if fam == "c" else FAMILY_CASES)]
    if {"a", "b"} <= {r.family for r in results}:
        # families (a) and (b) together: the damping target counts the runs on each plant type
        groups += [("a+b", label) for label, *_ in FAMILY_CASES]
    for fam, label in groups:
        rs = [r for r in results if r.case == label and r.family in fam.split("+")]
        if not rs:
            continue
        fault = [r.fault_delay_s for r in rs if r.fault_delay_s is not None]
        out["faults"].append({
            "family": fam, "case": label, **_detections(rs),
            "fault_delay_s_median": float(np.median(fault)) if fault else None,
            "fault_delay_s_worst": float(max(fault)) if fault else None,
            "fault_level_reached": len(fault),
            "false_alarms_before_fault": sum(r.false_alarms for r in rs),
            **_wrong_kind(rs),
            "withheld_before_fault": _withheld(rs, "withheld_before_fault"),
            "withheld_after_fault": _withheld(rs, "withheld_after_fault"),
            # per plant type: a linear model fitted to a shaft with backlash is a mismatched model
            "by_plant": {kind: _detections(sub) for kind in PLANT_TYPES
                         if (sub := [r for r in rs if ("backlash" in r.effects) == (kind == "backlash")])},
        })
    crossings = crossing_summary(results)
    if crossings is not None:
        out["crossings"] = crossings
    back = [t for r in results for t in revalid_after_changes(r)]
    out["revalid_after_change_s"] = ({"changes": len(back), "median": float(np.median(back)),
                                      "p90": float(np.quantile(back, 0.9)), "max": float(max(back))}
                                     if back else None)
    return out


def _wrong_kind(rs: list[RunResult]) -> dict[str, int]:
    """Alarms of the other kind than the fault's after it: runs with one, runs where one came before any
    alarm of the fault's kind (or with none of that kind), and how many."""
    wrong = [r for r in rs if r.wrong_kind_delay_s is not None]
    return {"wrong_kind_runs": len(wrong),
            "wrong_kind_first": sum(1 for r in wrong if r.warning_delay_s is None
                                    or r.wrong_kind_delay_s < r.warning_delay_s),
            "wrong_kind_alarms": sum(r.wrong_kind_alarms for r in rs)}


def crossing_summary(results: list[RunResult]) -> dict[str, Any] | None:
    """What the service did at the operating points where an engine-order line crosses the resonance
    (:data:`CROSSING_OUTCOMES`), and the false alarms there against those elsewhere; None: no run visited one."""
    visits = [(r, v) for r in results for v in r.crossings]
    if not visits:
        return None

    def hours(vs) -> float:
        return sum(v["t_end_s"] - v["t_start_s"] for _, v in vs) / 3600.0

    def outcomes(vs) -> dict[str, int]:
        return {k: n for k in CROSSING_OUTCOMES if (n := sum(1 for _, v in vs if v["outcome"] == k))}

    def valid(vs) -> float | None:
        n = sum(v["estimates"] for _, v in vs)
        return sum(v["valid"] for _, v in vs) / n if n else None

    free = [(r, v) for r, v in visits if r.case == "fault-free"]
    pre = [(r, v) for r, v in visits if r.case != "fault-free" and not v["after_fault"]]
    post = [(r, v) for r, v in visits if v["after_fault"]]
    n_free = sum(len(v["alarms"]) for _, v in free)
    free_runs = [r for r in results if r.case == "fault-free" and r.crossings]
    h_away = sum(r.duration_s for r in free_runs) / 3600.0 - hours(free)
    n_away = sum(r.false_alarms for r in free_runs) - n_free
    faults = [r for r in results if r.case != "fault-free" and any(v["after_fault"] for v in r.crossings)]
    first_at = sum(1 for r in faults if r.warning_delay_s is not None and any(
        v["after_fault"] and v["outcome"] in ("warned", "detected")
        and any(abs(a["t_s"] - (r.t_fault_s + r.warning_delay_s)) < 1e-9 for a in v["alarms"])
        for v in r.crossings))
    return {
        "runs": len({(r.case, r.seed, r.family) for r, _ in visits}), "visits": len(visits),
        "orders": sorted({v["order"] for _, v in visits}),
        "fault_free": {"visits": len(free), "hours": hours(free), "false_alarms": n_free,
                       **rate_per_1000h(n_free, hours(free)), "valid_fraction": valid(free),
                       "outcomes": outcomes(free)},
        "fault_free_elsewhere": {"hours": h_away, "false_alarms": n_away, **rate_per_1000h(n_away, h_away)},
        "before_fault": {"visits": len(pre), "hours": hours(pre), "false_alarms": sum(len(v["alarms"]) for _, v in pre),
                         "valid_fraction": valid(pre), "outcomes": outcomes(pre)},
        "after_fault": {"visits": len(post), "hours": hours(post), "valid_fraction": valid(post),
                        "outcomes": outcomes(post), "fault_runs": len(faults), "first_alarm_at_crossing": first_at},
    }


def rate_per_1000h(events: int, hours: float, level: float = 0.95) -> dict[str, Any]:
    r"""False alarms per 1,000 hours with its exact (Garwood) Poisson interval at ``level``.

    Notes
    -----
    For :math:`n` events in :math:`T` hours the interval of the rate is
    :math:`[\chi^2_{2n}(\alpha/2) / 2T,\ \chi^2_{2n+2}(1-\alpha/2) / 2T]`
    (the lower end 0 for :math:`n = 0`): with no false alarm in 3,000 hours the
    upper end is 1.23 per 1,000 hours.
    """
    if not hours > 0:
        return {"false_alarms_per_1000h": None, "false_alarms_per_1000h_ci": None}
    from scipy.stats import chi2

    a = 1.0 - level
    lo = 0.0 if events == 0 else float(chi2.ppf(a / 2.0, 2 * events)) / 2.0
    hi = float(chi2.ppf(1.0 - a / 2.0, 2 * events + 2)) / 2.0
    k = 1000.0 / hours
    return {"false_alarms_per_1000h": events * k, "false_alarms_per_1000h_ci": [lo * k, hi * k]}


def _withheld(rs: list[RunResult], name: str) -> dict[str, int] | None:
    """The alarms withheld in ``rs`` (field ``name`` of each run), summed per kind; None where no run recorded
    them (a results.json of a version before the count)."""
    total: dict[str, int] = {}
    for r in rs:
        for kind, n in (getattr(r, name) or {}).items():
            total[kind] = total.get(kind, 0) + int(n)
    return total or None


def revalid_after_changes(res: RunResult, gap_s: float = 1.5, within_s: float = 8.0) -> list[float]:
    """Seconds from the start of each change of operating point to the estimate's first valid estimate
    after it stopped being valid, in a fault run (from its 1 Hz ``zeta_trace`` of valid estimates and the
    scenario's operating points, rebuilt from the seed; fault-free runs keep no trace: none).

    The invalid stretch is the first gap of more than ``gap_s`` in the trace that begins within
    ``within_s`` of the change (the estimate stays valid for the first moments of a ramp).
    """
    if res.case == "fault-free" or not res.zeta_trace:
        return []
    spec = fault_spec(res.seed, res.case) if res.family == "c" else family_spec(res.seed, res.case, res.family)
    t = np.asarray([p[0] for p in res.zeta_trace], dtype=float)
    out, t_change = [], 0.0
    for point in spec.scenario.operating_points[:-1]:
        t_change += point.duration_s
        i = max(int(np.searchsorted(t, t_change)) - 1, 0)
        for j in range(i, t.size - 1):
            if t[j] > t_change + within_s:
                break
            if t[j + 1] - t[j] > gap_s:
                out.append(float(t[j + 1] - t_change))
                break
        t_change += spec.scenario.ramp_s
    return out


PLANT_TYPES = ("backlash", "no backlash")


def _detections(rs: list[RunResult]) -> dict[str, Any]:
    """Runs, detections and warning delays (median, worst) of ``rs``."""
    warn = [r.warning_delay_s for r in rs if r.warning_delay_s is not None]
    zs = [r.zeta_summary() for r in rs]

    def median(key: str) -> float | None:
        v = [z[key] for z in zs if z[key] is not None]
        return float(np.median(v)) if v else None

    return {"runs": len(rs), "detected": len(warn), "missed": len(rs) - len(warn),
            "warning_delay_s_median": float(np.median(warn)) if warn else None,
            "warning_delay_s_worst": float(max(warn)) if warn else None,
            "zeta_spread_pct_median": median("spread_pct"), "zeta_change_pct_median": median("change_pct")}
