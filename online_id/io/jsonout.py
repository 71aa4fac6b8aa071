"""Strict JSON out: numpy scalars and arrays as Python numbers and lists, non-finite floats as ``null``.

JSON has no NaN or Infinity; ``json.dumps`` writes them by default and strict parsers reject the
document.  Every JSON document a command prints or writes goes through :func:`dumps`.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def plain(obj: Any) -> Any:
    """``obj`` with numpy scalars and arrays as Python numbers and lists, non-finite floats as None."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [plain(v) for v in obj]
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def dumps(obj: Any, **kwargs: Any) -> str:
    """Strict JSON text of ``obj`` (see :func:`plain`); ``kwargs`` as for :func:`json.dumps`."""
    return json.dumps(plain(obj), allow_nan=False, **kwargs)
