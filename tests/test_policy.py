"""The detection policy stands on its own: built from the settings, a worker, a clock and an event log (no
pipeline), it restores and saves its part of a state document, and takes the commands and the input samples
through its interface."""

from collections import deque
from pathlib import Path

import pytest

from online_id.config import DetectionSettings, Settings
from online_id.estimation.model import ArmaxOrders
from online_id.io.statefile import load_state
from online_id.service.offload import InlineWorker
from online_id.service.policy import DetectionPolicy

SAVED = Path(__file__).parent / "data" / "state_v1.json"  # see tests/data/README.md


def _policy(settings: Settings) -> tuple[DetectionPolicy, list]:
    submitted = []
    policy = DetectionPolicy(settings, dt=0.005, worker=InlineWorker(),
                             submit_window=lambda fn, args, done: submitted.append(fn), clock=lambda: 0.0,
                             events=deque(maxlen=100), record=lambda alert, out, data=None: out.append(alert))
    return policy, submitted


def _n_params(settings: Settings) -> int:
    m = settings.model
    return ArmaxOrders(m.na, m.nb, m.nc, m.nk).n_params


def test_the_policy_restores_and_saves_its_items_of_a_state_document_unchanged():
    settings = Settings()
    saved = load_state(SAVED)
    policy, _ = _policy(settings)
    policy.load(saved, _n_params(settings))
    again = policy.to_dict()
    assert list(again) == ["baseline", "detector", "tracker", "healthy_rpm", "engaged", "references", "windows"]
    fresh, _ = _policy(settings)
    fresh.load(again, _n_params(settings))
    assert fresh.to_dict() == again
    assert policy.baseline.nonlinear and policy.detector.active is not None and policy.checks.windows


def test_acknowledge_releases_the_latched_alarm_and_relearn_forgets_the_baselines():
    settings = Settings()
    policy, _ = _policy(settings)
    policy.load(load_state(SAVED), _n_params(settings))
    policy.acknowledge()
    assert policy.detector.active is None and policy.baseline.bands  # the baselines stay
    policy.load(load_state(SAVED), _n_params(settings))
    policy.relearn()
    assert policy.detector.active is None and not policy.baseline.bands
    assert not policy.checks.references and not policy.checks.windows and not policy.engaged.summary()["learned"]


@pytest.mark.parametrize("backlash_test_s, kept", [(0.0, 0), (10.0, 3)])
def test_the_backlash_tests_samples_are_kept_only_while_a_test_may_run(backlash_test_s, kept):
    policy, _ = _policy(Settings(detection=DetectionSettings(backlash_test_s=backlash_test_s)))
    for k in range(3):
        policy.keep_sample(0.001 * k, 150.0, 150.0, 20.0)
    assert len(policy.backlash.samples) == kept
    policy.keep_sample(1.0, 150.0, 150.0, 20.0, restart=True)  # the stream broke: the samples before go
    assert len(policy.backlash.samples) == (1 if kept else 0)
