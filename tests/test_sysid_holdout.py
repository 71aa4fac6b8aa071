"""identify validates on held-out data by default: the split, and that no fit sees a held-out sample."""

import dataclasses

import numpy as np
import pytest

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.estimation import identification as ident
from online_id.estimation.identification import GUARD, HOLDOUT, identify, split_plateau
from online_id.estimation.settings import IdentificationSettings, InertiaSettings


def test_split_holds_out_a_quarter_in_one_piece_beside_the_window():
    dt = 0.002
    rng = np.random.default_rng(0)
    for size_s, fit_s in ((37.0, 40.0), (70.0, 40.0), (8.0, 40.0), (37.0, None), (120.0, 20.0)):
        u = rng.standard_normal(int(size_s / dt))
        (a, b), held = split_plateau(u, None if fit_s is None else int(fit_s / dt), HOLDOUT, dt)
        assert held is not None
        assert held[1] <= a - GUARD or held[0] >= b + GUARD  # apart from the window by the filter's reach
        assert held[1] - held[0] >= np.ceil(HOLDOUT * u.size) - GUARD
        assert (b - a) * dt == pytest.approx(min(fit_s or np.inf, (1 - HOLDOUT) * size_s), abs=dt)


def test_without_holdout_a_short_plateau_is_all_fit_window():
    u = np.random.default_rng(1).standard_normal(18500)
    window, held = split_plateau(u, 20000, 0.0, 0.002)
    assert window == (0, 18500) and held is None


def _bench(seed, points=((1000.0, 18.0), (1800.0, 18.0))):
    sc = dataclasses.replace(BenchScenario(), seed=seed,
                             operating_points=tuple(OperatingPoint(s, d) for s, d in points))
    return simulate_bench(sc).to_data("sim")


SETTINGS = IdentificationSettings(na=(8,))


@pytest.mark.slow
def test_held_out_fit_is_computed_on_samples_no_fit_saw(monkeypatch):
    """Change the measured dyno speed on the held-out samples only: every fit stays, the held-out fit moves.

    The fitted arrays are recorded too: none holds a held-out sample.  The same change inside the fit
    window moves the fit (the test can fail).
    """
    data = _bench(31)
    seen = []
    real_two, real_armax = ident.fit_two_starts, ident.fit_armax

    def spy_two(y, u, *a, **k):
        seen.append(y.size)
        return real_two(y, u, *a, **k)

    def spy_armax(y, u, *a, **k):
        seen.append(y.size)
        return real_armax(y, u, *a, **k)

    monkeypatch.setattr(ident, "fit_two_starts", spy_two)
    monkeypatch.setattr(ident, "fit_armax", spy_armax)
    base = identify(data, SETTINGS, InertiaSettings(J1=0.8), refine_s=60.0)
    factor = round(base.points[0].dt / float(np.median(np.diff(data.time_s))))
    for p in base.points:
        assert p.check is not None and p.check.held_out and p.check.span == p.held_out
        assert p.held_out[1] <= p.window[0] - GUARD or p.held_out[0] >= p.window[1] + GUARD
        # the refit (refine_s) grew beyond the window but stopped short of the held-out piece
        assert p.fit.n + p.fit.orders.max_lag <= p.plateau.stop - p.plateau.start
    assert max(seen) < min(round((p.plateau.stop - p.plateau.start) / factor) for p in base.points)

    def corrupted(where):
        y = data.dyno_speed_rad_s.copy()
        rng = np.random.default_rng(7)
        for p in base.points:
            a, b = getattr(p, where)
            raw = slice(p.plateau.start + a * factor, p.plateau.start + b * factor)
            y[raw] += 3.0 * np.std(y[raw]) * rng.standard_normal(y[raw].size)
        return dataclasses.replace(data, dyno_speed_rad_s=y)

    held = identify(corrupted("held_out"), SETTINGS, InertiaSettings(J1=0.8), refine_s=60.0)
    for p, q in zip(base.points, held.points):
        assert (q.window, q.held_out) == (p.window, p.held_out)
        np.testing.assert_allclose(q.fit.theta, p.fit.theta, rtol=1e-9, atol=1e-12)
        assert q.check.fit_pred_pct < p.check.fit_pred_pct - 20  # the held-out fit sees the change
    assert held.driveline.f0_hz == pytest.approx(base.driveline.f0_hz, rel=1e-12)
    window = identify(corrupted("window"), SETTINGS, InertiaSettings(J1=0.8), refine_s=60.0)
    assert any(not np.allclose(q.fit.theta, p.fit.theta, rtol=1e-6) for p, q in zip(base.points, window.points))


@pytest.mark.slow
def test_identify_validates_on_another_recording_and_prints_fit_bounds_and_intervals(tmp_path, capsys):
    """One command gives the held-out fit, the residual bounds and the parameter intervals (docs/sysid.md)."""
    import json

    from online_id.cli import main

    for name, seed in (("a", 41), ("b", 42)):
        (tmp_path / f"{name}.yaml").write_text("operating_points:\n  - {speed_rpm: 1100, duration_s: 16}\n"
                                              f"  - {{speed_rpm: 1900, duration_s: 16}}\nseed: {seed}\n")
        assert main(["simulate", "--config", str(tmp_path / f"{name}.yaml"), "--out", str(tmp_path / f"{name}.csv")]) == 0
    capsys.readouterr()
    args = ["identify", str(tmp_path / "a.csv"), "--J1", "0.8", "--na", "8", "--resid", "--validate",
            str(tmp_path / "b.csv")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "held out" in out and "simulation fit" in out and "99 % bounds" in out and "outside +-0.0" in out
    assert "c_s  =" in out and "+-" in out and "[95 % interval]" in out
    assert f"Validation on {tmp_path / 'b.csv'}" in out
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = doc["validation_file"]["points"]
    assert [round(r["model_speed_rpm"], -2) for r in rows] == [1100, 1900]
    assert all(r["fit_one_step_pct"] > 80 for r in rows)
    for p in doc["operating_points"]:
        v, r = p["validation"], p["resid"]
        assert v["held_out"] and v["window_s"][0] >= p["held_out_s"][0] - 1e-9
        assert r["autocorrelation_bound"] == pytest.approx(2.576 / np.sqrt(r["n_samples"]), rel=1e-3)
        assert len(r["cross_correlation"]) == 51 and r["cross_correlation_bound"] > 0
    d = doc["driveline"]
    assert d["ci95"]["c_s"][0] < d["c_s"] < d["ci95"]["c_s"][1] and d["std"]["J1"] is None


def test_bad_holdout_and_batch_flags_with_recursive_are_one_line(cli_error, tmp_path):
    csv = tmp_path / "none.csv"
    assert "--holdout" in cli_error(["identify", str(csv), "--holdout", "1.5"])
    assert "--resid, --mat" in cli_error(["identify", str(csv), "--recursive", "--resid", "--mat", "m.mat"])
