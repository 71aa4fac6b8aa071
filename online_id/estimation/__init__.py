"""Estimation: ARMAX models fitted to data, recursively (RELS, Kalman) and in batch (PEM).

Numerical only: numpy, scipy, numba and filterpy; no python-can, cantools,
files or clocks. Depends on :mod:`online_id.analysis` (poles, physical
parameters, operating points), never on :mod:`online_id.monitoring`.
"""
