"""The defaults of the detection settings, in one place: ``online_id.config.DetectionSettings`` takes its defaults
from here, and the baseline, the change detector and the engaged flank take theirs from here too (constants only;
this module imports nothing, so the configuration loads no numerical code)."""

BAND_RPM = 250.0
"""Width of a baseline's speed band [rpm]."""
LOAD_BAND_NM = 2.0
"""Width of a baseline cell's load band [Nm]."""
MIN_COUNT = 20
"""Estimates a baseline cell learns from before it is compared with."""
POOL_TOLERANCE_PCT = 0.5
"""Neighbouring cells whose resonance agrees within this [%] pool their statistics."""
K = 0.5
"""CUSUM allowance [standard deviations]."""
H_WARNING = 8.0
"""CUSUM level of a warning."""
H_FAULT = 16.0
"""CUSUM level of a fault."""
MIN_FREQ_CHANGE_PCT = 0.5
"""Dead band of the resonance [%]: a smaller relative deviation from the baseline counts as none."""
MIN_DAMPING_CHANGE_PCT = 20.0
"""Dead band of the damping ratio [%]."""
