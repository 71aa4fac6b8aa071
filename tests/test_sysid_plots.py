"""Plot defects, checked where a figure can be checked: legends off the data, labels inside the axes, tick
numbers, unwrapped phase, no empty time span, tracks and order lines named as they are."""

import numpy as np
import pytest

from online_id.monitoring.cells import BandStats
from online_id.report.figures import AlertMark, EngagedSeries, EstimateSeries, TrackSeries


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions make, drawn but not written."""
    import online_id.report.identification as pid
    import online_id.report.figures as rep

    kept = []

    def keep(fig, path, title=""):
        fig.canvas.draw()
        kept.append(fig)

    monkeypatch.setattr(rep, "save_figure", keep)
    monkeypatch.setattr(pid, "save_figure", keep)
    yield kept
    import matplotlib.pyplot as plt

    for f in kept:
        plt.close(f)


def _inside(inner, outer, tol=1.0):
    return (inner.x0 >= outer.x0 - tol and inner.x1 <= outer.x1 + tol and inner.y0 >= outer.y0 - tol
            and inner.y1 <= outer.y1 + tol)


def _overlap(a, b):
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


@pytest.fixture(scope="module")
def identified():
    import dataclasses

    from online_id.bench.scenario import BenchScenario, OperatingPoint
    from online_id.bench.simulate import simulate_bench
    from online_id.estimation.identification import identify
    from online_id.estimation.settings import IdentificationSettings

    sc = dataclasses.replace(BenchScenario(), seed=21,
                             operating_points=(OperatingPoint(1100.0, 16.0), OperatingPoint(1900.0, 16.0)))
    data = simulate_bench(sc).to_data("sim")
    return identify(data, IdentificationSettings(na=(8,))), data


def test_compare_legend_beside_the_data_and_measured_on_top(identified, figures, tmp_path):
    from online_id.report.identification import write_identification_plots

    result, data = identified
    write_identification_plots(result, data, tmp_path, resid=True)
    fig = next(f for f in figures if "held-out data" in f.axes[0].get_title())
    for ax in fig.axes:
        assert "never fitted" in ax.get_title()
        leg = ax.get_legend().get_window_extent()
        assert not _overlap(leg, ax.get_window_extent())  # the legend covers no data
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        measured = lines["measured"]
        assert all(measured.get_zorder() > ln.get_zorder() for k, ln in lines.items() if k != "measured")
    bode = [f for f in figures if "H1 from" in f.axes[0].get_title()]
    assert len(bode) == len(result.points)
    for f in bode:  # the model's phase is unwrapped: no jump of a half turn between neighbouring frequencies
        phase = next(ln for ln in f.axes[1].get_lines() if ln.get_label().startswith("model")).get_ydata()
        assert np.max(np.abs(np.diff(phase))) < 180.0
        assert "unwrapped" in f.axes[1].get_ylabel()
    resid = next(f for f in figures if "autocorrelation of the residual" in f.axes[0].get_title())
    assert len(resid.axes) == 2 * len(result.points)
    steps = next(f for f in figures if f.axes[0].get_title().startswith("step"))
    assert len(steps.axes[0].get_lines()) >= len(result.points)


def _track(tid, cls, f, order=None, t0=0.0, n=50):
    t = t0 + np.arange(n, dtype=float)
    speed = np.linspace(1000, 2000, n)
    fh = np.full(n, f) if order is None else order * speed / 60.0
    return TrackSeries(tid, cls, order, t, speed, fh, np.full(n, 0.05))


def test_all_tracked_poles_names_order_lines_and_no_far_driveline(figures, tmp_path):
    from online_id.report.figures import plot_versus_speed

    est = EstimateSeries(np.arange(50.0), np.linspace(1000, 2000, 50), np.full(50, 25.0), np.full(50, 0.05),
                         np.ones(50, bool))
    tracks = [_track(1, "driveline", 25.0), _track(2, "driveline", 150.0), _track(3, "speed_dependent", 0, 2.0)]
    plot_versus_speed(tmp_path / "f.png", "f0", est, tracks, (), 20)
    ax_all = figures[-1].axes[0]
    labels = ax_all.get_legend_handles_labels()[1]
    assert labels.count("driveline track") == 1  # the 150 Hz track is not called driveline
    assert any(lab.startswith("other track") for lab in labels)
    assert any(lab.startswith("order-line track") for lab in labels)
    texts = [t for t in ax_all.texts if t.get_text().strip() == "order 2"]
    assert texts and all(_inside(t.get_window_extent(), ax_all.get_window_extent()) for t in texts)


def _band():
    return BandStats(band=(1375.0, 1625.0), count=80, mean_f=25.0, std_f=0.05, mean_zeta=0.05, std_zeta=0.001)


def test_state_report_time_axis_has_no_empty_span_and_labels_stay_inside(figures, tmp_path):
    from online_id.report.figures import plot_tracks_over_time

    tracks = [_track(1, "driveline", 25.0, t0=40.0)]
    alerts = [AlertMark(0.5, 2, "freq_drift fault"), AlertMark(40.2, 1, "freq_drift warning"),
              AlertMark(92.0, 0, "onset of the active alarm")]
    plot_tracks_over_time(tmp_path / "t.png", None, tracks, (_band(),), alerts, "stream time [s]")
    ax_f = figures[-1].axes[0]
    lo, hi = ax_f.get_xlim()
    assert lo >= 40.0 - 0.05 * 52 and hi <= 92.0 + 0.05 * 52  # from the data to the near alert, not from 0
    box = ax_f.get_window_extent()
    for t in ax_f.texts:
        assert _inside(t.get_window_extent(), box), t.get_text()
    assert any("before the data shown" in t.get_text() for t in ax_f.texts)


def test_tracks_over_time_shows_the_engaged_readings_that_raised_an_alarm(figures, tmp_path):
    from online_id.report.figures import plot_tracks_over_time

    est = EstimateSeries(np.arange(100.0), np.full(100, 1500.0), np.full(100, 25.0), np.full(100, 0.05),
                         np.ones(100, bool))
    eng = EngagedSeries(np.array([10.0, 30.0, 60.0, 75.0]), np.array([26.0, 26.01, 25.2, 25.1]),
                        np.full(4, 0.05), np.array([False, False, True, True]), 26.0, 0.05)
    plot_tracks_over_time(tmp_path / "t.png", est, [], (_band(),), [AlertMark(75.0, 2, "frequency fault")],
                          "time [s]", engaged=eng)
    ax_f = figures[-1].axes[0]
    line = next(ln for ln in ax_f.get_lines() if ln.get_label() == "engaged-flank readings that raised an alarm")
    assert list(line.get_xdata()) == [60.0, 75.0]
    assert "engaged-flank readings that raised an alarm" in [t.get_text() for t in ax_f.get_legend().get_texts()]


def test_residual_spectrum_panels_have_tick_numbers(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from online_id.report.residuals import psd_before_after

    f = np.linspace(0, 250, 500)
    fig, axes = plt.subplots(2, 1, sharex=True)
    for ax in axes:
        psd_before_after(ax, f, 1e-4 * (1.5 + np.sin(f / 30)), 1e-4 * (1.4 + np.sin(f / 30)), "rpm^2/Hz")
    fig.canvas.draw()
    for ax in axes:
        assert [t.get_text() for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]
        assert len([t for t in ax.get_yticklabels() if t.get_visible() and t.get_text()]) >= 2
    plt.close(fig)
