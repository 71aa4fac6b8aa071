"""Wear trends (online_id.archive.trend, `online-id trend`): onset dating, no trend on healthy benches, the
live service's alert wording, the plots and the fleet table."""

import datetime as dt
import json

import numpy as np
import pytest

from online_id.archive.trend import NONE, STEP, WEAR, TrendSettings, fit_change, operating_points, trends
from online_id.cli import main

START = dt.datetime(2025, 1, 6, tzinfo=dt.timezone.utc)


def bench_rows(bench, seed, *, onset_day=None, wear_per_month=0.0, step=0.0, n=50, days=182.0, scatter=0.003,
               speeds=(1200.0, 1800.0, 2500.0), f0=25.0, zeta=0.05):
    """Table rows of a bench: ``n`` recordings over ``days``, each at ``speeds``; the stiffness falls by
    ``wear_per_month`` (relative) from ``onset_day`` on, or jumps by ``step``; ``scatter`` is the relative
    day-to-day scatter of the stiffness (the resonance moves by half of it)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        day = (k + rng.uniform(0.1, 0.9)) * days / n
        stiff = 1.0
        if onset_day is not None and day >= onset_day:
            stiff = 1.0 - wear_per_month * (day - onset_day) / 30.0 if wear_per_month else 1.0 + step
        stiff *= 1.0 + scatter * rng.standard_normal()
        damp = 1.0 + (1.0 - stiff if wear_per_month else 0.0)
        when = START + dt.timedelta(days=float(day))
        for i, s in enumerate(speeds):
            out.append({"bench": bench, "status": "ok", "start_time": when, "path": f"/a/{bench}/{k}.mf4",
                        "sha256": f"{bench}-{k}", "segment": 0, "op_index": i,
                        "speed_rpm": s + rng.uniform(-10, 10),
                        "f0_hz": f0 * np.sqrt(stiff) * (1 + 3e-4 * rng.standard_normal()),
                        "zeta": zeta * damp / np.sqrt(stiff) * (1 + 0.01 * rng.standard_normal())})
    return out


@pytest.mark.parametrize("seed", range(8))
def test_wear_is_dated_within_a_week_and_healthy_benches_show_none(seed):
    rng = np.random.default_rng([seed, 7])
    onset = float(rng.uniform(30.0, 110.0))
    rate = float(rng.uniform(0.02, 0.06))
    jump_day = float(rng.uniform(40.0, 150.0))
    rows = (bench_rows("H", seed) + bench_rows("W", seed + 100, onset_day=onset, wear_per_month=rate)
            + bench_rows("F", seed + 200, onset_day=jump_day, step=-float(rng.uniform(0.08, 0.2)))
            + bench_rows("H2", seed + 300, f0=31.0, speeds=(1000.0, 2900.0)))
    got = {b.bench: b for b in trends(rows)}
    assert got["H"].level == 0 and got["H"].verdict() == "no trend"
    assert got["H2"].level == 0 and got["H2"].verdict() == "no trend"
    for name, truth, model in (("W", onset, WEAR), ("F", jump_day, STEP)):
        b = got[name]
        onset_day = (b.onset_s() - START.timestamp()) / 86400.0
        assert abs(onset_day - truth) < 7.0, (name, onset_day, truth)
        assert b.level >= 1
        freq = [s for s in b.series if s.kind == "frequency"]
        assert all(s.fit.model == model for s in freq)
    # the drift per month is the true resonance's mean slope since the onset (its interval is conditional on
    # the onset and on a straight line, where the resonance follows the square root of a linear stiffness loss)
    for s in (s for s in got["W"].series if s.kind == "frequency"):
        span = s.days()[-1] - (onset - (s.t0_s - START.timestamp()) / 86400.0)
        secant = 100.0 * (np.sqrt(1.0 - rate * span / 30.0) - 1.0) / span * 30.4
        assert s.drift_pct_per_month == pytest.approx(secant, rel=0.1), (s.drift_pct_per_month, secant)
        assert s.drift_ci[0] < s.drift_pct_per_month < s.drift_ci[1]
    for s in got["H"].series + got["H2"].series:  # no drift beyond about three of its standard errors
        lo, hi = s.drift_ci
        assert s.fit.model == NONE and abs(s.drift_pct_per_month) <= 1.5 * (hi - lo), s.as_row()
        assert (hi - lo) < (0.1 if s.kind == "frequency" else 1.0)


def test_fit_change_finds_a_step_a_hinge_and_nothing():
    t = np.arange(40.0)
    r = np.where(t >= 20.5, -3.0, 0.0)
    best, *_ = fit_change(t, r)
    assert best.model == STEP and best.t0 == pytest.approx(20.5) and best.step == pytest.approx(-3.0)
    r = -0.1 * np.maximum(0.0, t - 12.0)
    best, _none, wear, _step = fit_change(t, r + 1e-4 * np.sin(t))
    assert best.model == WEAR and abs(wear.t0 - 12.0) <= 0.5 and wear.slope == pytest.approx(-0.1, rel=0.02)
    best, *_ = fit_change(t, 1e-3 * np.random.default_rng(1).standard_normal(t.size))
    assert best.model == NONE or abs(best.at(t[-1]) - best.a) < 0.5


def test_alerts_speak_the_live_service_language():
    rows = bench_rows("W", 5, onset_day=50.0, wear_per_month=0.05)
    (b,) = trends(rows)
    freq = sorted((s for s in b.series if s.kind == "frequency"), key=lambda s: s.speed_rpm)
    s = freq[0]
    assert s.level == 2
    assert s.message.startswith("fault: driveline frequency ") and " % lower (stiffness about " in s.message
    when = dt.datetime.fromtimestamp(s.onset_s, dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    assert s.message.endswith(f"since {when} at {s.speed_rpm:.0f} rpm")
    # the alert's date is where the fitted change first passes the fault level, after the onset
    assert s.onset_s < s.alert_s <= s.time_s[-1]
    assert abs(s.fit.at((s.alert_s - s.t0_s) / 86400.0)) == pytest.approx(2.5, abs=0.01)
    damping = [x for x in b.series if x.kind == "damping"]
    assert all(x.change_pct > 0 for x in damping)


def test_operating_points_group_jittered_speeds():
    ops = operating_points(np.array([1195.0, 1805, 1210, 2490, 1790, 2510, 1200]), 100.0)
    assert sorted(set(ops.tolist())) == [1200.0, 1797.5, 2500.0]
    with pytest.raises(ValueError):
        TrendSettings(warn_freq_pct=3.0, fault_freq_pct=2.0)


def test_trend_command_writes_plots_and_the_fleet_table(tmp_path, capsys):
    pytest.importorskip("pyarrow")
    from online_id.archive.store import write_table
    from online_id.archive.table import blank_row

    rows = bench_rows("B01", 1) + bench_rows("B02", 2, onset_day=60.0, wear_per_month=0.04)
    table = [blank_row(**{k: v for k, v in r.items()}) for r in rows]
    table.append(blank_row(bench="B02", path="/a/bad.mf4", status="error", error="bad.mf4: no such channel"))
    write_table(table, tmp_path / "results.parquet", tmp_path / "results.csv")
    out = tmp_path / "trend"
    assert main(["trend", str(tmp_path / "results.parquet"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| B01 | no trend | - |" in text
    assert "| B02 | fault: driveline frequency" in text
    assert (out / "trend_B01.png").stat().st_size > 10000 and (out / "trend_B02.png").stat().st_size > 10000
    doc = json.loads((out / "trend.json").read_text())
    assert [b["level"] for b in doc["benches"]] == [0, 2]
    assert doc["rows_used"] == len(rows)
    lines = (out / "fleet.csv").read_text().splitlines()
    assert lines[0].startswith("bench,quantity,speed_rpm") and len(lines) == 1 + 2 * 2 * 3
    # the CSV export reads alike; one bench only
    assert main(["trend", str(tmp_path / "results.csv"), "--bench", "B02", "--out", str(tmp_path / "t2"),
                 "--json"]) == 0
    doc2 = json.loads(capsys.readouterr().out)
    assert [b["bench"] for b in doc2["benches"]] == ["B02"]
    assert doc2["benches"][0]["onset"] == doc["benches"][1]["onset"]
    assert main(["trend", str(tmp_path / "results.csv"), "--bench", "B09", "--out", str(tmp_path / "t3")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "no bench 'B09'" in err and "B01, B02" in err and err.count("\n") == 1
