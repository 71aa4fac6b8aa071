"""Numerical core: estimators, pole analysis, operating points.

Nothing in this package performs I/O or imports python-can or cantools; it
depends only on numpy, scipy, numba and filterpy.
"""
