"""Exported models: in the JSON and a .mat (idpoly layout), loaded by scipy and python-control, simulate as the fit."""

import json

import numpy as np
import pytest
from scipy.io import loadmat
from scipy.signal import lfilter

from online_id.cli import main
from online_id.estimation.export import transfer_functions, z_polynomials
from online_id.io.model_mat import read_models_mat, write_models_mat

control = pytest.importorskip("control")

BENCH = """
operating_points:
  - {speed_rpm: 1100, duration_s: 14}
  - {speed_rpm: 1900, duration_s: 14}
seed: 12
"""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    (d / "s.yaml").write_text(BENCH)
    assert main(["simulate", "--config", str(d / "s.yaml"), "--out", str(d / "bench.csv")]) == 0
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["identify", str(d / "bench.csv"), "--na", "8", "--json", "--mat", str(d / "m.mat")]) == 0
    return json.loads(buf.getvalue()), d / "m.mat"


def test_json_models_simulate_in_python_control_as_the_fit(exported):
    doc, _ = exported
    rng = np.random.default_rng(0)
    for point in doc["operating_points"]:
        m = point["model"]
        assert m["A"][0] == 1.0 and m["C"][0] == 1.0 and m["B"][:m["input_delay_samples"]] == [0.0]
        assert m["sample_time_s"] == pytest.approx(0.002) and m["input_unit"] == "Nm" and m["output_unit"] == "rad/s"
        g, h = transfer_functions(m)
        assert g.dt == m["sample_time_s"]
        u = rng.standard_normal(30)  # the model as identified may hold an unstable (spurious) pole: a short input
        np.testing.assert_allclose(control.forced_response(g, U=u).outputs, lfilter(m["B"], m["A"], u), rtol=1e-7,
                                   atol=1e-9)
        poles = np.sort_complex(control.poles(g))
        roots = np.sort_complex(np.roots(m["A"]))
        np.testing.assert_allclose(poles[np.abs(poles) > 1e-9], roots[np.abs(roots) > 1e-9], rtol=1e-6)
        assert m["unstable_poles"] == int(np.sum(np.abs(roots) > 1.0))
        driveline = [q for q in point["poles"] if q["class"] == "driveline"]
        if driveline:  # python-control's damp() gives the frequency the table gives
            wn, zeta, _ = control.damp(g, doprint=False)
            assert np.min(np.abs(wn / (2 * np.pi) - driveline[0]["f_hz"])) < 1e-6 * driveline[0]["f_hz"]


def test_simulation_model_reproduces_the_fits_simulated_output(exported):
    """The exported B_sim/A_sim in python-control gives the simulated output identify's compare drew."""
    from online_id.analysis.poles import SPEED_DEPENDENT
    from online_id.ingest.benchlog import read_bench
    from online_id.config import Settings
    from online_id.estimation.identification import compare_point, identify, point_signals
    from online_id.estimation.pem import simulate_model
    from online_id.estimation.settings import IdentificationSettings
    from online_id.estimation.validation import cancel_pairs, stable_theta

    doc, mat = exported
    data = read_bench(mat.parent / "bench.csv", Settings(), lambda _n: None)
    result = identify(data, IdentificationSettings(na=(8,)))
    for p, point in zip(result.points, doc["operating_points"]):
        g, _ = transfer_functions(point["model"], simulation=True)
        assert np.all(np.abs(control.poles(g)) <= 1.0)
        y, u = point_signals(data, p)
        c = compare_point(p, y, u, p.check.span)
        a, b = p.check.span
        uu = u[a:b] - np.mean(u[a:b])
        theta, _ = stable_theta(cancel_pairs(p.fit, [q.z for q in p.poles if q.cls == SPEED_DEPENDENT])[0],
                                p.fit.orders)
        forced = simulate_model(uu, p.fit.orders, theta)  # compare's simulation from rest
        np.testing.assert_allclose(control.forced_response(g, U=uu).outputs, forced, rtol=1e-7,
                                   atol=1e-9 * np.max(np.abs(forced)))
        # and compare's simulated output is that plus the free response of its fitted initial state
        assert np.corrcoef(c.y_sim - forced, c.y)[0, 1] < 1.0
        assert p.check.fit_sim_pct == pytest.approx(point["validation"]["fit_simulation_pct"])


def test_mat_file_is_read_by_loadmat_in_the_idpoly_layout(exported):
    doc, mat = exported
    raw = loadmat(str(mat), squeeze_me=True, struct_as_record=False)
    models = np.atleast_1d(raw["models"])
    assert len(models) == len(doc["operating_points"])
    for m, point in zip(models, doc["operating_points"]):
        want = point["model"]
        np.testing.assert_array_equal(np.atleast_1d(m.A), want["A"])
        np.testing.assert_array_equal(np.atleast_1d(m.B), want["B"])
        np.testing.assert_array_equal(np.atleast_1d(m.C), want["C"])
        assert m.Ts == want["sample_time_s"] and m.OutputUnit == "rad/s" and m.InputName == "dyno_torque"
    assert raw["driveline"].f0_hz == pytest.approx(doc["driveline"]["f0_hz"])
    loaded = read_models_mat(mat)
    u = np.random.default_rng(1).standard_normal(500)
    for m, point in zip(loaded, doc["operating_points"]):
        g, _ = transfer_functions(m)
        np.testing.assert_allclose(control.forced_response(g, U=u).outputs, lfilter(point["model"]["B"],
                                   point["model"]["A"], u), rtol=1e-8, atol=1e-12)


def test_z_polynomials_pad_to_one_length():
    num, den = z_polynomials([0.0, 2.0], [1.0, -0.5, 0.1])
    assert num.tolist() == [0.0, 2.0, 0.0] and den.tolist() == [1.0, -0.5, 0.1]


def test_bad_mat_file_is_one_line(tmp_path):
    from online_id.errors import InputDataError

    bad = tmp_path / "x.mat"
    bad.write_text("not a mat file")
    with pytest.raises(InputDataError, match="x.mat"):
        read_models_mat(bad)
    write_models_mat(tmp_path / "empty.mat", [], None)
    assert read_models_mat(tmp_path / "empty.mat") == []
