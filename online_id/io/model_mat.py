"""Identified models as a MATLAB ``.mat`` file (``scipy.io.savemat``) that ``idpoly`` takes, and back.

Layout (MATLAB 5 format): ``models`` is a 1 x K struct array, one element per
operating point, with the fields

============== =====================================================
A, B, C        row vectors in increasing powers of q^-1 (A(1) = C(1) = 1;
               B starts with ``nk`` zeros: the input delay), as identified
ASim, BSim     the stable model ``compare`` simulates (order-line pole-zero
               pairs removed, unstable poles reflected)
UnstablePoles  how many poles of A lie outside the unit circle
Ts             sample time [s]
nk             input delay [samples] (already in B's leading zeros)
NoiseVariance  variance of e [(rad/s)^2]
InputName      'dyno_torque'; InputUnit 'Nm' (positive brakes)
OutputName     'dyno_speed'; OutputUnit 'rad/s'
InputOffset    the operating point's mean torque [Nm]
OutputOffset   the operating point's mean dyno speed [rad/s]
EngineSpeed    the operating point's engine speed [rpm]
TStart, TEnd   the operating point in the recording [s]
============== =====================================================

and ``driveline`` is a struct of the driveline parameters (``f0_hz``,
``zeta``, ``c_s``, ``d_s``, ``J1``, ``J2`` and their ``*_std``; NaN where
unknown).  In MATLAB::

    s = load('models.mat');
    m = s.models(1);
    sys = idpoly(m.A, m.B, m.C, 1, 1, m.NoiseVariance, m.Ts, ...
                 'InputName', m.InputName, 'InputUnit', m.InputUnit, ...
                 'OutputName', m.OutputName, 'OutputUnit', m.OutputUnit);
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from online_id.errors import InputDataError

# MATLAB field <- key of the exported model (online_id.estimation.export.point_model)
FIELDS = {
    "A": "A", "B": "B", "C": "C", "ASim": "A_sim", "BSim": "B_sim", "UnstablePoles": "unstable_poles",
    "Ts": "sample_time_s", "nk": "input_delay_samples",
    "NoiseVariance": "noise_variance", "InputName": "input", "InputUnit": "input_unit", "OutputName": "output",
    "OutputUnit": "output_unit", "InputOffset": "input_offset", "OutputOffset": "output_offset",
    "EngineSpeed": "engine_speed_rpm", "TStart": "t_start_s", "TEnd": "t_end_s",
}
VECTORS = ("A", "B", "C", "ASim", "BSim")


def write_models_mat(path: str | Path, models: Sequence[Mapping], driveline: Mapping | None = None) -> None:
    """Write ``models`` (dicts of :func:`online_id.estimation.export.point_model`) and ``driveline`` to ``path``."""
    from scipy.io import savemat

    arr = np.zeros((1, len(models)), dtype=[(name, object) for name in FIELDS])
    for k, m in enumerate(models):
        for name, key in FIELDS.items():
            value = m.get(key)
            if name in VECTORS:
                value = np.asarray(value, dtype=float).reshape(1, -1)
            elif isinstance(value, str):
                pass
            else:
                value = float("nan") if value is None else float(value)
            arr[0, k][name] = value
    doc: dict = {"models": arr, "format": "online-id identified models: see models(k).A/B/C/Ts for idpoly"}
    if driveline is not None:
        doc["driveline"] = {k: (float("nan") if v is None else float(v)) for k, v in driveline.items()
                            if v is None or isinstance(v, (int, float))}
    try:
        savemat(str(path), doc, oned_as="row")
    except OSError as err:
        raise InputDataError(f"{path}: cannot write the model file ({err.strerror or err})") from err


def read_models_mat(path: str | Path) -> list[dict]:
    """The models of a file written by :func:`write_models_mat`, as dicts with the keys of the export."""
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    try:
        doc = loadmat(str(path), squeeze_me=False, struct_as_record=True)
    except FileNotFoundError:
        raise InputDataError(f"{path}: cannot read: no such file") from None
    except (OSError, ValueError, TypeError, MatReadError) as err:
        raise InputDataError(f"{path}: expected a MATLAB .mat file of online-id models, but it cannot be read "
                             f"({err})") from None
    if "models" not in doc:
        raise InputDataError(f"{path}: expected a variable \"models\" (online-id identify --mat), found "
                             + (", ".join(k for k in doc if not k.startswith("__")) or "none"))
    arr = doc["models"]
    missing = [n for n in ("A", "B", "C", "Ts") if n not in (arr.dtype.names or ())]
    if missing:
        raise InputDataError(f"{path}: the struct \"models\" lacks the field(s) {', '.join(missing)}")
    out = []
    for el in arr.ravel():
        m = {}
        for name, key in FIELDS.items():
            if name not in arr.dtype.names:
                continue
            v = np.asarray(el[name])
            if name in VECTORS:
                m[key] = v.astype(float).ravel().tolist()
            elif v.dtype.kind in "US":
                m[key] = str(v.ravel()[0]) if v.size else ""
            else:
                m[key] = float(v.ravel()[0]) if v.size else None
        for key in ("input_delay_samples", "unstable_poles"):
            if m.get(key) is not None:
                m[key] = int(m[key])
        out.append(m)
    return out
