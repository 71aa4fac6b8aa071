"""Residual diagnosis: find what a fitted model lacks, add it, report the error.

The core of ``online-id diagnose``: numpy/scipy only, no file I/O.
"""

from online_id.diagnose.data import DiagnoseData
from online_id.diagnose.diagnosis import Diagnosis, EffectStep, ErrorFigures, diagnose

__all__ = ["DiagnoseData", "Diagnosis", "EffectStep", "ErrorFigures", "diagnose"]
