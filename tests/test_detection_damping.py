"""Damping changes with a mismatched model (issue 15, part 4): the confirm keeps the baseline's own minimum
where the window does not tell it from the best (nearly equal minima of a shaft with backlash)."""

from types import SimpleNamespace

import numpy as np
import pytest

from online_id.estimation import window
from online_id.estimation.model import ArmaxOrders


@pytest.mark.parametrize("v_last,within,wins", [
    (1.004, 0.01, "last"),  # a near tie: the caller's (baseline's) minimum is kept
    (1.004, 0.0, "hannan-rissanen"),  # without the preference the lowest loss wins, as before
    (1.03, 0.01, "hannan-rissanen"),  # the data reject the baseline's minimum: the best fit wins
    (0.98, 0.01, "last"),  # the baseline's minimum is the best anyway
])
def test_the_baseline_minimum_is_kept_where_the_window_cannot_tell_the_minima_apart(monkeypatch, v_last, within,
                                                                                     wins):
    losses = {None: 1.0, "other": 1.2, "last": v_last}

    def fake_fit(y, u, orders, theta0=None, **kw):
        name = None if theta0 is None else ("last" if theta0[0] == 2.0 else "other")
        return SimpleNamespace(V=losses[name], name=name or "hannan-rissanen")

    monkeypatch.setattr(window, "fit_armax", fake_fit)
    y = np.zeros(100)
    fit = window.fit_two_starts(y, y, ArmaxOrders(4, 4, 2, 1), recursive_start=False,
                                starts=(np.array([1.0]), None, np.array([2.0])), prefer_last_within=within)
    assert fit.name == wins


def test_a_failed_last_start_is_never_preferred(monkeypatch):
    def fake_fit(y, u, orders, theta0=None, **kw):
        if theta0 is not None and theta0[0] == 2.0:
            raise window.EstimationError("diverged")
        return SimpleNamespace(V=1.0 if theta0 is None else 1.001, name="hr" if theta0 is None else "first")

    monkeypatch.setattr(window, "fit_armax", fake_fit)
    y = np.zeros(100)
    fit = window.fit_two_starts(y, y, ArmaxOrders(4, 4, 2, 1), recursive_start=False,
                                starts=(np.array([1.0]), np.array([2.0])), prefer_last_within=0.01)
    assert fit.name == "hr"  # the first start's fit is not the caller's: the lowest loss wins
