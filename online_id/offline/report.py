"""A report of a replayed log or a saved state: the data collected, plots, report.json and report.md, the
residual tests and the results as MDF 4 (the work of ``online-id report``).

From a CAN log (``.log``, ``.asc``, ``.blf``) the frames go through
:func:`online_id.offline.replay.replay` exactly as in ``online-id replay``; a
:class:`RecordingRuntime` observes every publication on its way to the
encoder and keeps the driveline estimates (with the engine speed at the time),
the points of the pole tracks and the alerts.  From a state file of the
service (``online-id-state.json``, :mod:`online_id.io.statefile`) there is no
series of estimates: the report shows the track histories, the baselines and
the latched alarm.

Written to ``DIR``: ``frequency_vs_speed.png`` and ``damping_vs_speed.png``
(the paper's Fig. 5 and 6), ``tracks_over_time.png``, ``report.json`` and
``report.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from online_id.io.jsonout import plain
from online_id.offline.replay import ResultsRuntime, replay
from online_id.config import Settings, load_config
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.cells import BandStats
from online_id.monitoring.detection import ChangeDetector
from online_id.monitoring.engaged import MIN_LEARNED as ENGAGED_MIN, EngagedFlank
from online_id.monitoring.tracks import PoleTracker
from online_id.errors import InputDataError, OnlineIdError
from online_id.io.canlog import SUFFIXES as LOG_SUFFIXES
from online_id.io.statefile import load_state
from online_id.records import AlertKind, AlertOut, EstimateOut, Publication
from online_id.report.figures import (
    AlertMark,
    EngagedSeries,
    EstimateSeries,
    TerminalProgress,
    TrackSeries,
    fmt,
    plot_tracks_over_time,
    plot_versus_speed,
)
from online_id.service.runtime import OutFrame

STATE_SUFFIXES = (".json",)
FIGURES = ("frequency_vs_speed.png", "damping_vs_speed.png", "tracks_over_time.png")
SEVERITY = {0: "info", 1: "warning", 2: "fault"}
# Units of the keys of report.json (written into it as "units"); keys without a unit are counts, names or flags.
REPORT_UNITS = {
    "t0_s": "s (stream time of the origin)", "t_s": "s", "t_first_s": "s", "t_last_s": "s",
    "first_valid_t_s": "s", "since_t_s": "s", "detected_t_s": "s", "replay_s": "s (wall time)",
    "speed_rpm": "rpm", "band_rpm": "rpm", "load_nm": "Nm", "f0_hz": "Hz", "f_hz": "Hz", "f0_std_hz": "Hz",
    "f0_uncertainty_hz": "Hz", "zeta": "1", "zeta_std": "1", "c_s": "Nm/rad", "d_s": "Nm s/rad",
    "J1": "kg m^2", "J2": "kg m^2", "value_pct": "%", "change_pct": "%", "spread_ratio": "1",
    "residual_rms": "rad/s (one-step prediction error of the dyno speed, RMS)",
    "fpe": "rad/s (square root of the final prediction error of the dyno speed)",
    "excitation_nm": "Nm (RMS of the torque excitation)", "learned_t_s": "s", "engine_speed_rpm": "rpm",
    "fit_one_step_pct": "%", "autocorrelation": "1", "cross_correlation": "1", "autocorrelation_bound": "1",
    "cross_correlation_bound": "1", "lags": "samples of the identification's rate", "cross_lags": "samples",
}
EPOCH_S = 1e8  # stream times above this are Unix times (a live service), below: seconds from a log start


# --- collected data ----------------------------------------------------------------------------------


@dataclass
class ReportData:
    """Everything the report shows; times are seconds from ``t0_s`` (a stream time)."""

    source: Path
    kind: str  # "can_log" or "state"
    t0_s: float
    estimates: EstimateSeries | None
    tracks: list[TrackSeries]
    baselines: tuple[BandStats, ...]
    min_count: int
    alerts: list[AlertOut]
    active_alarm: dict | None
    final: dict
    learned_t_s: dict[tuple, float] | None = None  # per baseline cell (cell_key), when it was learned; None: unknown
    extra: dict = field(default_factory=dict)
    runtime: RecordingRuntime | None = None  # the replay's (a CAN log), for --out-mf4
    engaged: EngagedSeries | None = None  # engaged-flank readings (shafts with backlash)
    identification: Any = None  # the offline identification of the log (--resid), for resid.png


class RecordingRuntime(ResultsRuntime):
    """A :class:`~online_id.service.runtime.Runtime` that keeps what the pipeline publishes.

    Every publication passes :meth:`frames` on its way to the encoder; the
    estimates are kept with the engine speed of the estimator at that moment
    and, per track matched at that publication, its newest point (once the
    pipeline has tracked it, on the sample after the publication).  Acknowledge
    and re-learn notices (alerts of kind NONE) are kept too; the raised alerts
    are the pipeline's own list (the 1 Hz repeats of a latched alarm are not
    new alerts).
    """

    def __post_init__(self) -> None:
        super().__post_init__()
        self.estimates: list[tuple[float, float, float, float, bool]] = []
        self.track_points: dict[int, list[tuple[float, float, float, float]]] = {}
        self.track_info: dict[int, tuple[str, float | None]] = {}
        self.notices: list[AlertOut] = []
        self.learned_at: dict[tuple, float] = {}  # baseline cell -> stream time it was first learned
        self._awaiting: float | None = None  # a publication whose tracking has not run yet
        self.engaged_readings: list = []  # the engaged flank's readings (shafts with backlash), as offered
        engaged = self.pipeline.engaged
        offer = engaged.offer

        def keep_reading(reading, learn):
            self.engaged_readings.append(reading)
            return offer(reading, learn)

        engaged.offer = keep_reading

    def frames(self, pubs: list[Publication]) -> list[OutFrame]:
        for pub in pubs:
            if isinstance(pub, EstimateOut):
                self.estimates.append((pub.t_s, self.pipeline.estimator.speed_rpm, pub.f0_hz, pub.zeta,
                                       bool(pub.valid)))
                self._awaiting = pub.t_s
            elif isinstance(pub, AlertOut) and pub.kind == AlertKind.NONE:
                self.notices.append(pub)
        return super().frames(pubs)

    def on_frame(self, *args, **kwargs) -> list[OutFrame]:
        out = super().on_frame(*args, **kwargs)
        if self._awaiting is not None and not self.pipeline.detection_pending:
            self._observe_tracks(self._awaiting)
        return out

    def tick(self, now_s: float) -> list[OutFrame]:
        out = super().tick(now_s)
        if self._awaiting is not None and not self.pipeline.detection_pending:
            self._observe_tracks(self._awaiting)
        return out

    def _observe_tracks(self, t_s: float) -> None:
        """Tracks and learned cells after the tracking of the publication at ``t_s`` (run on the sample after it)."""
        self._awaiting = None
        p = self.pipeline
        for b in p.baseline.bands:
            if b.count >= p.baseline.min_count:
                self.learned_at.setdefault(cell_key(b), t_s)
        for tr in p.tracker.tracks:
            self.track_info[tr.id] = (tr.cls, tr.order)
            if tr.last_seen_s == t_s:  # matched (or started) at this publication
                self.track_points.setdefault(tr.id, []).append((tr.last_seen_s, tr.speed_rpm, tr.f_hz, tr.zeta))


def cell_key(b: BandStats) -> tuple:
    """What identifies a baseline cell: its speed band and load."""
    return (float(b.band[0]), float(b.band[1]), round(float(b.load_nm), 6) if math.isfinite(b.load_nm) else None)


def _fin(x: Any) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None


def _series(rows: list[tuple], t0: float) -> np.ndarray:
    arr = np.array(rows, dtype=float).reshape(-1, 4)
    arr[:, 0] -= t0
    return arr


def from_log(path: Path, settings: Settings) -> ReportData:
    """Replay the log through the service pipeline and collect the report data."""
    runtime = RecordingRuntime(settings)
    progress = TerminalProgress("report")
    t_wall = time.monotonic()
    try:
        replay(str(path), runtime, progress=progress)
    finally:
        progress.close()
    pipe = runtime.pipeline
    if not runtime.estimates:
        c = pipe.counters
        bad = ", ".join(f"{k.name.lower()} {v}" for k, v in c.faults.items() if v) or "none"
        raise InputDataError(
            f"{path}: expected dyno speed, engine speed and dyno torque frames of the DBC, but got "
            f"{runtime.frames_in} frames, {c.samples} samples and no estimate (unused frames: {bad})")
    t0 = pipe.t_first or 0.0
    est = np.array(runtime.estimates, dtype=float).reshape(-1, 5)
    estimates = EstimateSeries(est[:, 0] - t0, est[:, 1], est[:, 2], est[:, 3], est[:, 4].astype(bool))
    tracks = []
    for tid, pts in sorted(runtime.track_points.items()):
        cls, order = runtime.track_info[tid]
        a = _series(pts, t0)
        tracks.append(TrackSeries(tid, cls, order, a[:, 0], a[:, 1], a[:, 2], a[:, 3]))
    result = pipe.result()
    final = final_estimate(result, estimates)
    alerts = sorted(list(pipe.alerts) + runtime.notices, key=lambda a: a.t_s)
    return ReportData(
        source=path, kind="can_log", t0_s=t0, estimates=estimates, tracks=tracks,
        baselines=pipe.baseline.bands, min_count=pipe.baseline.min_count,
        alerts=[dataclasses.replace(a, t_s=a.t_s - t0) for a in alerts],
        active_alarm=_alarm_dict(pipe.detector, t0), final=final,
        learned_t_s={k: v - t0 for k, v in runtime.learned_at.items()},
        runtime=runtime, engaged=engaged_series(runtime.engaged_readings, pipe.engaged, t0),
        extra={"frames_in": runtime.frames_in, "frames_out": runtime.frames_out,
               "replay_s": round(time.monotonic() - t_wall, 3), "quality": result["quality"],
               "counters": result["counters"], "status_changes": result["status_changes"],
               "engaged_flank": pipe.engaged.summary()},
    )


def engaged_series(readings: list, flank: EngagedFlank, t0: float) -> EngagedSeries | None:
    """The engaged flank's readings, those inside a confirmed change marked (None without readings)."""
    if not readings:
        return None
    t = np.array([r.t_s for r in readings], dtype=float)
    alarm = np.zeros(t.size, dtype=bool)
    for ch in flank.changes:
        alarm |= (t >= ch.since_t_s) & (t <= ch.detected_t_s)
    ref = flank.reference()
    return EngagedSeries(t - t0, np.array([r.f0_hz for r in readings]), np.array([r.zeta for r in readings]), alarm,
                         ref["f0_hz"] if ref else None, ref["zeta"] if ref else None)


def final_estimate(result: dict, estimates: EstimateSeries) -> dict:
    """The last estimate of a replay (``result``: :meth:`Pipeline.result`): valid only if the service ended TRACKING.

    A service that ended in INPUT_TIMEOUT, LEARNING, ... holds its last
    estimate; the report says so instead of calling it valid.
    """
    final = dict(result["driveline"], state=result["state"], t_s=float(estimates.t_s[-1]), source="estimator")
    if final.get("valid") and result["state"] != "TRACKING":
        ok = estimates.valid
        final["valid"] = False
        final["why"] = f"the service ended in {result['state']}" + (
            f"; the values are its last estimate, valid last at t = {estimates.t_s[ok][-1]:.1f} s" if ok.any() else "")
    return final


def _alarm_dict(detector: ChangeDetector, t0: float) -> dict | None:
    a = detector.active
    if a is None:
        return None
    d = a.as_dict()
    d["since_t_s"] -= t0
    d["detected_t_s"] -= t0
    return d


def from_state(path: Path) -> ReportData:
    """Read a state file of the service and collect the report data."""
    state = load_state(path)
    if not isinstance(state, dict) or not {"baseline", "detector", "tracker"} <= state.keys():
        if isinstance(state, dict):
            got = "the keys " + ", ".join(f'"{k}"' for k in sorted(state)) if state else "an empty object"
        else:
            got = f"a JSON {type(state).__name__}"
        raise InputDataError(f"{path}: expected a state file of online-id with \"baseline\", \"detector\" and "
                             f"\"tracker\", but got {got}")
    try:
        baseline = Baseline.from_dict(state["baseline"])
        engaged = EngagedFlank.from_dict(state.get("engaged"))
        detector = ChangeDetector.from_dict(state["detector"])
        tracker = PoleTracker.from_dict(state["tracker"])
        raw_alerts = [AlertOut(**(a | {"kind": AlertKind(a["kind"])})) for a in state.get("alerts", [])]
    except OnlineIdError as err:
        raise InputDataError(f"{path}: {err}") from err
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
        raise InputDataError(f"{path}: saved state is incomplete or malformed ({err!r})") from err
    times = [float(t) for tr in tracker.tracks for t in tr.history.t_s if math.isfinite(t)]
    times += [a.t_s for a in raw_alerts]
    t0 = min(times) if times and min(times) > EPOCH_S else 0.0  # Unix times from a live service: from the oldest
    tracks, reclassed = [], []
    for tr in tracker.tracks:
        h = tr.history
        cls = tr.cls
        if cls == "driveline" and far_from_baselines(tr.f_hz, baseline.bands):
            cls = "unknown"
            reclassed.append({"id": tr.id, "f_hz": _fin(tr.f_hz), "why": "classed driveline by the tracker, but more "
                              f"than {100 * FAR_FROM_BASELINE:.0f} % from every learned baseline frequency"})
        tracks.append(TrackSeries(tr.id, cls, tr.order, h.t_s - t0, h.speed_rpm, h.f_hz, h.zeta))
    drive = tracker.driveline()
    if drive is not None and far_from_baselines(drive.f_hz, baseline.bands):
        drive = None
    final = {"f0_hz": None, "zeta": None, "valid": None, "source": "no driveline track"
             + (" near the learned baselines" if reclassed else "")}
    if drive is not None:
        final = {"f0_hz": _fin(drive.f_hz), "zeta": _fin(drive.zeta), "speed_rpm": _fin(drive.speed_rpm),
                 "t_s": _fin(drive.last_seen_s - t0), "valid": None,
                 "source": f"driveline track {drive.id} (confidence {drive.confidence:.2f})"}
    final["why"] = ("a state file holds the pole tracks, not the service's last estimate nor its health state "
                    "(e.g. INPUT_TIMEOUT): whether the estimate was valid is not known; replay the log for that")
    engaged_pts = engaged_series(list(engaged.learned), engaged, t0)
    return ReportData(
        source=path, kind="state", t0_s=t0, estimates=None, tracks=tracks, baselines=baseline.bands, engaged=engaged_pts,
        min_count=baseline.min_count, alerts=[dataclasses.replace(a, t_s=a.t_s - t0) for a in raw_alerts],
        active_alarm=_alarm_dict(detector, t0), final=final,
        extra={"state_version": state.get("version"), "tracks_reclassed": reclassed,
               "engaged_flank": engaged.summary()},
    )


FAR_FROM_BASELINE = 0.10  # a "driveline" track this far (relative) from every baseline frequency is not the driveline


def far_from_baselines(f_hz: float, baselines: tuple[BandStats, ...]) -> bool:
    """True when baselines exist and ``f_hz`` lies more than :data:`FAR_FROM_BASELINE` from all of them."""
    return bool(baselines) and all(abs(f_hz - b.mean_f) > FAR_FROM_BASELINE * b.mean_f for b in baselines)


def load_source(path: Path, config: str | None) -> ReportData:
    """The report data of a CAN log or a state file, told apart by suffix (then by content)."""
    if not path.exists():
        raise InputDataError(f"{path}: cannot read: no such file")
    if not path.is_file():
        raise InputDataError(f"{path}: expected a CAN log or a state file, but got a directory")
    settings = load_config(config)
    suffix = path.suffix.lower()
    if suffix in LOG_SUFFIXES:
        return from_log(path, settings)
    if suffix in STATE_SUFFIXES or _looks_like_json(path):
        return from_state(path)
    raise InputDataError(
        f"{path}: expected a CAN log ({', '.join(LOG_SUFFIXES)}) or a state file (.json), "
        f"but got {path.suffix or 'no suffix'!r}")


def _looks_like_json(path: Path) -> bool:
    try:
        with path.open("rb") as fh:
            head = fh.read(64).lstrip()
    except OSError as err:
        raise InputDataError(f"{path}: cannot read: {err.strerror or err}") from err
    return head.startswith(b"{")


# --- outputs ----------------------------------------------------------------------------------------


_plain = plain  # strict JSON (non-finite floats as null)


def _stats(x: np.ndarray) -> dict | None:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return None
    return {"median": float(np.median(x)), "min": float(x.min()), "max": float(x.max())}


def _band_dict(b: BandStats, min_count: int, learned_t_s: dict[tuple, float] | None) -> dict:
    out = b.as_dict() | {"learned": b.count >= min_count and b.kind != "held"}
    if learned_t_s is not None:
        out["learned_t_s"] = learned_t_s.get(cell_key(b))
    return out


def _alert_dict(a: AlertOut) -> dict:
    return {"t_s": _fin(a.t_s), "kind": a.kind.name, "severity": int(a.severity),
            "level": SEVERITY.get(int(a.severity), str(a.severity)), "value_pct": _fin(a.value_pct),
            "speed_rpm": _fin(a.speed_rpm), "message": a.message}


def summary_t0(data: ReportData) -> str:
    """The time origin as an ISO 8601 UTC date (for Unix stream times)."""
    return datetime.fromtimestamp(data.t0_s, timezone.utc).isoformat(timespec="seconds")


def summary(data: ReportData) -> dict:
    """The JSON-able summary written to ``report.json``."""
    out: dict[str, Any] = {"source": str(data.source), "kind": data.kind, "t0_s": data.t0_s}
    if data.t0_s > EPOCH_S:
        out["t0_utc"] = summary_t0(data)
    e = data.estimates
    counts = {"estimates": len(e) if e is not None else 0,
              "valid_estimates": int(e.valid.sum()) if e is not None else 0,
              "tracks": len(data.tracks), "track_points": int(sum(t.t_s.size for t in data.tracks)),
              "baseline_bands": len(data.baselines),
              "learned_bands": sum(b.count >= data.min_count for b in data.baselines),
              "alerts": len(data.alerts), "warnings": sum(a.severity == 1 for a in data.alerts),
              "faults": sum(a.severity >= 2 for a in data.alerts)}
    out["counts"] = counts
    if e is not None and len(e):
        ok = e.valid  # statistics of the valid estimates
        out["estimates"] = {"t_first_s": float(e.t_s[0]), "t_last_s": float(e.t_s[-1]),
                            "first_valid_t_s": float(e.t_s[ok][0]) if ok.any() else None,
                            "speed_rpm": _stats(e.speed_rpm[ok]), "f0_hz": _stats(e.f0_hz[ok]),
                            "zeta": _stats(e.zeta[ok])}
    out["baselines"] = [_band_dict(b, data.min_count, data.learned_t_s) for b in data.baselines]
    out["tracks"] = [{"id": t.id, "class": t.cls, "order": t.order, "points": int(t.t_s.size),
                      "t_first_s": _fin(t.t_s[0]) if t.t_s.size else None,
                      "t_last_s": _fin(t.t_s[-1]) if t.t_s.size else None,
                      "f_hz": _stats(t.f_hz), "zeta": _stats(t.zeta)} for t in data.tracks]
    out["alerts"] = [_alert_dict(a) for a in data.alerts]
    out["active_alarm"] = data.active_alarm
    out["final_estimate"] = data.final
    out.update(data.extra)
    out["figures"] = list(FIGURES) + (["resid.png"] if data.identification is not None else [])
    out["units"] = dict(REPORT_UNITS)
    return out


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _section(title: str, header: str, align: str, empty: str, rows: list[str]) -> list[str]:
    """A Markdown section: a table of ``rows``, or the sentence ``empty`` when there are none."""
    return ["", f"## {title}", ""] + ([header, align, *rows] if rows else [empty])


def markdown(data: ReportData, doc: dict) -> str:
    """A short Markdown summary: figures, final estimate, baselines, alerts."""
    c = doc["counts"]
    what = "CAN log replayed through the service pipeline" if data.kind == "can_log" else "state file of the service"
    lines = [f"# online-id report: {data.source.name}", "",
             f"Source: `{data.source}` ({what}).", ""]
    if data.kind == "can_log":
        lines.append(f"{c['estimates']} estimates published, {c['valid_estimates']} valid; "
                     f"{c['tracks']} pole tracks; {c['alerts']} alerts "
                     f"({_plural(c['warnings'], 'warning')}, {_plural(c['faults'], 'fault')}). Times are seconds from the first sample.")
    else:
        when = (f"Times are seconds from the oldest track point or alert, {doc['t0_utc']}." if "t0_utc" in doc
                else "Times are the stream's (seconds from the start of the log or bus).")
        lines.append(f"{c['tracks']} live pole tracks ({c['track_points']} points); {c['alerts']} recent alerts. "
                     + when)
    lines += ["", "## Figures", ""]
    titles = ("Driveline frequency against engine speed (paper Fig. 5)",
              "Damping ratio against engine speed (paper Fig. 6)",
              "Frequency and damping over time, baselines and alerts")
    for name, title in zip(FIGURES, titles):
        lines.append(f"- [{title}]({name})")
    f = data.final
    valid = {True: "yes", False: "no", None: "unknown"}[f.get("valid")]
    lines += ["", "## Final estimate", "", "| f0 [Hz] | zeta [-] | valid | from |", "|---:|---:|:---:|---|",
              f"| {fmt(f.get('f0_hz'), '.3f')} | {fmt(f.get('zeta'), '.4f')} "
              f"| {valid} | {f.get('source', '')} |"]
    if f.get("why"):
        lines += ["", f"Valid: {valid}: {f['why']}."]
    lines += _section("Baselines", "| band [rpm] | load [Nm] | f0 [Hz] | std f0 [Hz] | zeta [-] | std zeta [-] | count "
                      "| status | learned from | spread / estimator uncertainty |",
                      "|---|---:|---:|---:|---:|---:|---:|:---:|---|---:|", "No baseline learned yet.", [
                          f"| {b['band_rpm'][0]:.0f}-{b['band_rpm'][1]:.0f} | {fmt(b['load_nm'], '.1f')} "
                          f"| {b['f0_hz']:.3f} | "
                          f"{b['f0_std_hz']:.3f} | {b['zeta']:.4f} | {b['zeta_std']:.4f} | {b['count']} | "
                          f"{b.get('kind', 'learned' if b['learned'] else 'learning')} | {b.get('source') or '-'} "
                          f"| {fmt(b.get('spread_ratio'), '.1f')} |" for b in doc["baselines"]])
    lines += _engaged_section(doc.get("engaged_flank"))
    lines += _resid_section(doc)
    lines += _section("Alerts", "| t [s] | kind | level | speed [rpm] | change [%] | message |",
                      "|---:|---|---|---:|---:|---|", "No alerts.", [
                          f"| {fmt(a['t_s'], '.1f')} | {a['kind']} | {a['level']} | "
                          f"{fmt(a['speed_rpm'], '.0f')} | {fmt(a['value_pct'], '+.1f')} | "
                          f"{a['message'].replace('|', '/')} |" for a in doc["alerts"]])
    alarm = doc["active_alarm"]
    lines += ["", "## Active alarm", "",
              f"{alarm['message']} (detected at t = {alarm['detected_t_s']:.1f} s, not acknowledged)."
              if alarm else "None.", ""]
    return "\n".join(lines)


def _engaged_section(e: dict | None) -> list[str]:
    """The engaged flank's reference (shafts with backlash, :mod:`online_id.monitoring.engaged`); none where the
    shaft showed no backlash."""
    if not e or not e.get("learned"):
        return []
    when = "" if e["usable"] else f" (compared with from {ENGAGED_MIN} readings on)"
    return ["", "## Engaged flank (shaft with backlash)", "",
            "| f0 [Hz] | zeta [-] | readings | spread stiffness [%] | spread zeta [%] | alarm below stiffness [%] "
            "| alarm beyond zeta [%] | learned from |", "|---:|---:|---:|---:|---:|---:|---:|---|",
            f"| {e['f0_hz']:.3f} | {e['zeta']:.4f} | {e['learned']}{when} | {e['std_k_pct']:.2f} "
            f"| {e['std_zeta_pct']:.1f} | -{e['threshold_k_pct']:.1f} | +-{e['threshold_zeta_pct']:.0f} "
            f"| {', '.join(e.get('sources') or []) or '-'} |"]


def write_report(data: ReportData, out: Path) -> list[Path]:
    """Write the figures, ``report.json`` and ``report.md`` to ``out``; returns the paths."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputDataError(f"{out}: cannot create the report directory: {err.strerror or err}") from err
    name = data.source.name
    paths = [out / f for f in FIGURES]
    try:
        plot_versus_speed(paths[0], "f0", data.estimates, data.tracks, data.baselines, data.min_count,
                          title=f"driveline frequency against engine speed, {name}")
        plot_versus_speed(paths[1], "zeta", data.estimates, data.tracks, data.baselines, data.min_count,
                          title=f"driveline damping against engine speed, {name}")
        marks = [AlertMark(a.t_s, int(a.severity), a.message if a.kind == AlertKind.NONE else
                           f"{a.kind.name.lower()} {SEVERITY.get(int(a.severity), '')}") for a in data.alerts]
        if data.active_alarm is not None:
            marks.append(AlertMark(data.active_alarm["since_t_s"], 0, "onset of the active alarm"))
        label = ("time from the first sample [s]" if data.kind == "can_log" else
                 f"time from {summary_t0(data)} [s]" if data.t0_s > EPOCH_S else "stream time [s]")
        learned = (None if data.learned_t_s is None else
                   [data.learned_t_s.get(cell_key(b), math.inf) for b in data.baselines])
        plot_tracks_over_time(paths[2], data.estimates, data.tracks, data.baselines, marks, label,
                              title=f"driveline estimate over time, {name}", learned_t_s=learned,
                              engaged=data.engaged)
        if data.identification is not None and any(p.resid is not None for p in data.identification.points):
            from online_id.report.identification import plot_resid

            paths.append(out / "resid.png")
            plot_resid(data.identification, paths[-1], title=f"residual tests per operating point, {name}")
        doc = summary(data)
        paths.append(out / "report.json")
        paths[-1].write_text(json.dumps(_plain(doc), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        paths.append(out / "report.md")
        paths[-1].write_text(markdown(data, doc), encoding="utf-8")
    except OSError as err:
        raise InputDataError(f"{out}: cannot write the report: {err.strerror or err}") from err
    return paths


def identify_residuals(data: ReportData, config: str | None) -> None:
    """``--resid``: identify the log per operating point (as ``identify``) and keep its residual tests."""
    from online_id.ingest.benchlog import read_bench
    from online_id.errors import EstimationError
    from online_id.estimation.identification import identify

    s = load_config(config)
    try:
        bench = read_bench(str(data.source), s, lambda _note: None)
        result = identify(bench, s.identification, s.inertias)
    except (InputDataError, EstimationError) as err:
        data.extra["resid"] = {"error": str(err)}
        return
    data.identification = result
    data.extra["resid"] = {"points": [
        {"engine_speed_rpm": p.speed_rpm, "held_out": bool(p.check and p.check.held_out),
         "fit_one_step_pct": p.check.fit_pred_pct if p.check else None,
         **(p.resid.as_dict() if p.resid is not None else {})} for p in result.points]}


def _resid_section(doc: dict) -> list[str]:
    r = doc.get("resid")
    if not r:
        return []
    if "error" in r:
        return ["", "## Residual tests", "", f"Not identified per operating point: {r['error']}"]
    rows = [f"| {p['engine_speed_rpm']:.0f} | {'held out' if p['held_out'] else 'fit window'} "
            f"| {fmt(p['fit_one_step_pct'], '.1f')} | {p.get('autocorrelation_outside', '-')}/"
            f"{len(p.get('lags', [0])) - 1} | +-{fmt(p.get('autocorrelation_bound'), '.3f')} "
            f"| {p.get('cross_correlation_outside', '-')}/{len(p.get('cross_lags', []))} "
            f"| +-{fmt(p.get('cross_correlation_bound'), '.3f')} |" for p in r["points"]]
    return _section("Residual tests", "| speed [rpm] | samples | one-step fit [%] | autocorrelation outside | "
                    "99 % bound | cross-correlation with the torque outside | 99 % bound |",
                    "|---:|---|---:|---:|---:|---:|---:|", "No operating point.", rows) + [
        "", "The log identified per operating point as `online-id identify` does; MATLAB's `resid` on the "
        "one-step residual ([resid.png](resid.png))."]


def write_results_mf4(data: ReportData, path: str) -> None:
    """``--out-mf4``: a log's publications (as ``replay --out-mf4``), or a state's alerts and track points."""
    from online_id.offline.replay import results_groups, write_results
    from online_id.io.mdf_results import Channel, ChannelGroup, TimeBase, write_results_mdf

    if data.runtime is not None:
        write_results(path, str(data.source), data.runtime, list(data.runtime.pipeline.alerts))
        return
    base = TimeBase(datetime.fromtimestamp(data.t0_s, timezone.utc) if data.t0_s > EPOCH_S else None, 0.0)
    alerts = [a for a in data.alerts]
    groups = [g for g in results_groups([], base, alerts) if g.name == "online-id alert"]
    pts = sorted((t, tr.id, tr.cls, n, f, z) for tr in data.tracks
                 for t, n, f, z in zip(tr.t_s, tr.speed_rpm, tr.f_hz, tr.zeta))
    classes = {0: "driveline", 1: "speed_dependent", 2: "unknown"}
    code = {v: k for k, v in classes.items()}
    groups.append(ChannelGroup("online-id pole tracks", np.array([p[0] for p in pts]), [
        Channel("oid_track_id", [p[1] for p in pts], "", "pole track"),
        Channel("oid_track_class", [code.get(p[2], 2) for p in pts], "", "class of the track", classes),
        Channel("oid_track_speed", [p[3] for p in pts], "rpm", "engine speed at the point"),
        Channel("oid_track_f", [p[4] for p in pts], "Hz", "pole frequency"),
        Channel("oid_track_zeta", [p[5] for p in pts], "", "pole damping ratio"),
    ], "the points of the pole tracks of the saved state"))
    write_results_mdf(path, groups, base, comment=f"online-id results of {data.source.name}")
