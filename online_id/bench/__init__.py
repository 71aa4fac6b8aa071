"""Test-bench simulator and excitation signals."""

from online_id.analysis.excitation import mls, prbs_signal
from online_id.bench.scenario import (
    Backlash,
    BenchScenario,
    Effects,
    Fault,
    Friction,
    Noise,
    OperatingPoint,
    PiGains,
    PrbsSettings,
    SensorDelay,
    SinusoidalDisturbance,
    StructuralResonance,
    ThirdInertia,
    TorqueRipple,
    load_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from online_id.bench.simulate import BenchRecord, simulate_bench

__all__ = [
    "Backlash", "BenchRecord", "BenchScenario", "Effects", "Fault", "Friction", "Noise",
    "OperatingPoint", "PiGains", "PrbsSettings", "SensorDelay", "SinusoidalDisturbance",
    "StructuralResonance", "ThirdInertia", "TorqueRipple", "load_scenario", "mls",
    "prbs_signal", "scenario_from_dict", "scenario_to_dict", "simulate_bench",
]
