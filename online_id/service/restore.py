"""Restoring the service's saved state: validated as a whole, used all or nothing.

:func:`restore_pipeline` reads the state file (:func:`~online_id.io.statefile.load_state`:
size limit, strict JSON, numeric arrays only), then checks it before any of
it is used:

1. **Schema.** The top level has exactly the keys a fresh
   :class:`~online_id.service.pipeline.Pipeline` saves (so the schema follows the
   code), each of the same kind (mapping, list, or a finite number or null),
   the version of the code, and the pipeline's own items (learned-from
   solutions and windows, alerts) well formed. The learned-from windows
   (``windows``) may be missing: a state saved before they were kept is
   restored without them.
2. **Trial.** The state is loaded into a scratch pipeline, which is then
   run on half a second of synthetic samples, published, summarised and
   saved again.  Anything that fails rejects the file.
3. Only then is the state loaded into the pipeline that is returned.

A rejected file is moved aside as ``<name>.bad-<UTC time>`` (the last
:data:`~online_id.io.statefile.KEEP_REJECTED` are kept) and the reason is
logged in one line; the service starts afresh, and its next save writes a new
file.  A file holding ``null`` is a reset: reported, and the service starts
afresh.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import numpy as np

from online_id.config import Settings
from online_id.estimation.reference import ReferenceWindow
from online_id.errors import InputDataError
from online_id.io.statefile import StateReset, _plain, keep_rejected, load_state
from online_id.service.persistence import STATE_VERSION
from online_id.service.pipeline import Pipeline
from online_id.records import ROLES, AlertKind, AlertOut, SignalSample

TRIAL_S = 0.5
OPTIONAL = ("windows",)
"""Top-level keys a state saved by an earlier release may lack (restored as the fresh pipeline's)."""
"""Seconds of synthetic samples the scratch pipeline runs on."""


class StateRejected(InputDataError):
    """The saved state breaks the schema or fails its trial (the message says where)."""


def _kind(value: object) -> str:
    if isinstance(value, dict):
        return "mapping"
    if isinstance(value, (list, np.ndarray)):
        return "list"
    if value is None or (isinstance(value, (int, float)) and not isinstance(value, bool)):
        return "number or null"
    return type(value).__name__


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_state(state: dict, settings: Settings) -> None:
    """Raise :class:`StateRejected` naming the first key that breaks the schema (see module notes)."""
    if state.get("version") != STATE_VERSION:
        raise StateRejected(f"version: expected {STATE_VERSION}, but got {state.get('version')!r:.40}")
    fresh = Pipeline(settings).get_state()
    state = {**{k: fresh[k] for k in OPTIONAL if k not in state}, **state}
    unknown = sorted(set(state) - set(fresh))
    missing = sorted(set(fresh) - set(state))
    if unknown or missing:
        raise StateRejected("expected the keys " + ", ".join(sorted(fresh))
                            + (f"; unknown: {', '.join(repr(k)[:40] for k in unknown)}" if unknown else "")
                            + (f"; missing: {', '.join(missing)}" if missing else ""))
    for key, value in fresh.items():
        want, got = _kind(value), _kind(state[key])
        if want != got:
            raise StateRejected(f"{key}: expected a {want}, but got a {got}")
        if want == "number or null" and state[key] is not None and not _number(state[key]):
            raise StateRejected(f"{key}: expected a finite number or null, but got {state[key]!r}")
    n = Pipeline(settings).estimator.orders.n_params
    for band, theta in state["references"].items():
        if not band.lstrip("-").isdigit() or _kind(theta) != "list" or len(theta) != n \
                or not all(_number(x) for x in theta):
            raise StateRejected(f"references.{band[:20]}: expected {n} finite numbers under an integer key")
    for band, windows in state["windows"].items():
        if not band.lstrip("-").isdigit() or _kind(windows) != "list" or not all(
                _kind(w) == "mapping" and ReferenceWindow.from_dict(w, n) is not None for w in windows):
            raise StateRejected(f"windows.{band[:20]}: expected a list of learned-from windows (samples y and u, "
                                f"{n} finite solution numbers, speed_rpm, load_nm, t_s) under an integer key")
    names = {f.name for f in fields(AlertOut)}
    for i, a in enumerate(state["alerts"]):
        ok = (isinstance(a, dict) and set(a) == names and isinstance(a["message"], str)
              and all(_number(a[k]) for k in ("t_s", "severity", "value_pct", "speed_rpm"))
              and a["kind"] in AlertKind._value2member_map_ and not isinstance(a["kind"], bool))
        if not ok:
            raise StateRejected(f"alerts[{i}]: expected an alert with {', '.join(sorted(names))}")


def _trial(state: dict, settings: Settings) -> None:
    """Run a scratch pipeline from ``state`` on synthetic samples; any failure rejects the state."""
    scratch = Pipeline(settings)
    scratch.load_state(copy.deepcopy(state))
    fs = settings.input.sample_rate_hz
    rng = np.random.default_rng(0)
    for k in range(int(TRIAL_S * fs)):
        t = k / fs
        values = (125.0 + 0.1 * rng.standard_normal(), 125.0, 20.0 * np.sign(np.sin(2 * np.pi * 7 * t)))
        for role, v in zip(ROLES, values):
            scratch.on_signal(SignalSample(role, float(v), t))
    scratch.estimator.estimate()
    scratch.result()
    json.dumps(_plain(scratch.get_state()), allow_nan=True)


def restore_pipeline(path: str | Path, settings: Settings, say: Callable[[str], None], worker=None) -> Pipeline | None:
    """A pipeline restored from the state file at ``path``, or None to start afresh (see module notes); its slow
    work goes to ``worker`` (default: inline, see :mod:`online_id.service.offload`)."""
    path = Path(path)
    try:
        state = load_state(path)
        if state is None:
            return None
        check_state(state, settings)
        try:
            _trial(state, settings)
            pipeline = Pipeline(settings, worker=worker)
            pipeline.load_state(state)
        except Exception as err:  # noqa: BLE001 - a file from disk fed to the estimators: any failure rejects it
            text = " ".join(str(err).split())[:200]
            raise StateRejected(f"fails to load or run: {type(err).__name__}: {text}") from err
    except StateReset as err:
        say(f"{err} (reset)")
        return None
    except InputDataError as err:
        reason = str(err).removeprefix(f"{path}: ")
        kept = keep_rejected(path)
        where = f"kept as {kept.name}" if kept is not None else "could not be moved aside"
        say(f"ignoring saved state {path}: {reason}; {where}; starting afresh")
        return None
    say(f"restored estimator state from {path}")
    return pipeline
