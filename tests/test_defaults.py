"""Defaults in one place: the detection settings and the detectors built without settings agree, because both
take their defaults from online_id.monitoring.defaults."""

import inspect

from online_id.config import DetectionSettings, Settings
from online_id.monitoring import defaults
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.detection import ChangeDetector
from online_id.monitoring.engaged import EngagedFlank
from online_id.service.pipeline import Pipeline


def _default(cls, name):
    return inspect.signature(cls.__init__).parameters[name].default


def test_the_settings_defaults_are_the_detectors_defaults():
    d = DetectionSettings()
    assert (d.k, d.h_warning, d.h_fault) == (_default(ChangeDetector, "k"), _default(ChangeDetector, "h_warning"),
                                             _default(ChangeDetector, "h_fault"))
    assert d.min_freq_change_pct / 100.0 == _default(ChangeDetector, "min_change_f")
    assert d.min_damping_change_pct / 100.0 == _default(ChangeDetector, "min_change_zeta")
    assert d.min_damping_change_pct / 100.0 == _default(EngagedFlank, "dead_band_zeta")
    assert (d.band_rpm, d.min_count, d.load_band_nm) == (_default(Baseline, "band_rpm"), _default(Baseline, "min_count"),
                                                         _default(Baseline, "load_band_nm"))
    assert d.pool_tolerance_pct / 100.0 == _default(Baseline, "pool_tolerance_f")


def test_a_pipeline_of_default_settings_builds_default_detectors():
    pipe = Pipeline(Settings())
    free = ChangeDetector(correlation_s=pipe.detector.correlation_s)
    for name in ("k", "h_warning", "h_fault", "min_change_f", "min_change_zeta"):
        assert getattr(pipe.detector, name) == getattr(free, name), name
    for name in ("band_rpm", "min_count", "load_band_nm", "pool_tolerance_f"):
        assert getattr(pipe.baseline, name) == getattr(Baseline(), name), name
    assert defaults.MIN_COUNT == pipe.baseline.min_count
