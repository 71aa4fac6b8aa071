"""Monitoring: pole tracks, learned baselines and change detection (wear and faults).

Numerical only; depends on :mod:`online_id.analysis`, never on
:mod:`online_id.estimation` (it is fed estimates, it does not make them).
"""
