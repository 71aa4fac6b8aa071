"""Analysis of identified models: poles and their sorting, physical parameters, operating points.

Numerical only, and the bottom of the numerical layers: it imports nothing
of the project but :mod:`online_id.errors` and :mod:`online_id.records`.
"""
