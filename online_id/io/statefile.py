"""Persisted state: JSON written atomically (temporary file, fsync, rename), read with limits.

Reading is strict, so that nothing half-understood is used: the file must be
at most :data:`MAX_STATE_BYTES`, UTF-8 JSON without duplicate keys, nested at
most :data:`MAX_DEPTH` deep, a mapping at the top level, and every saved
array (``{"__array__": [...], "dtype": ...}``) rectangular and of a numeric
dtype (:data:`ARRAY_DTYPES`; never ``object``).  A file holding ``null``
is an explicit reset (:class:`StateReset`).  What the mapping must hold is
checked by the consumer (:mod:`online_id.service.restore`).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from online_id.errors import InputDataError

MAX_STATE_BYTES = 16 * 1024 * 1024
"""Largest state file read (a service's state is about 0.1 MB; the limit leaves room for many baselines)."""
MAX_DEPTH = 32
ARRAY_DTYPES = frozenset({"float64", "float32", "int64", "int32", "int16", "int8", "uint8", "bool"})
KEEP_REJECTED = 5
"""Rejected state files kept beside the state file (``<name>.bad-<UTC time>``), newest first."""


class StateReset(InputDataError):
    """The state file holds ``null``: start afresh (reported, not an error of the file)."""


def _plain(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return {"__array__": obj.tolist(), "dtype": str(obj.dtype)}
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def _revive(obj: Any, where: str = "", depth: int = 0) -> Any:
    if depth > MAX_DEPTH:
        raise ValueError(f"{where or 'top level'}: nested more than {MAX_DEPTH} deep")
    if isinstance(obj, dict):
        if "__array__" in obj:
            dtype = obj.get("dtype", "float64")
            if set(obj) - {"__array__", "dtype"} or dtype not in ARRAY_DTYPES:
                raise ValueError(f"{where}: expected an array of dtype {', '.join(sorted(ARRAY_DTYPES))}, "
                                 f"but got dtype {str(dtype)[:40]!r}")
            try:
                return np.asarray(obj["__array__"], dtype=dtype)
            except (TypeError, ValueError, OverflowError) as err:
                raise ValueError(f"{where}: not a rectangular {dtype} array ({err})") from None
        return {k: _revive(v, f"{where}.{k}" if where else k, depth + 1) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_revive(v, f"{where}[{i}]", depth + 1) for i, v in enumerate(obj)]
    return obj


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    out: dict = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"duplicate key {k!r}")
        out[k] = v
    return out


def save_state(path: str | Path, state: dict) -> None:
    """Write ``state`` to ``path`` atomically: a crash leaves the old file or the new one, never half."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_plain(state), allow_nan=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_state(path: str | Path, max_bytes: int = MAX_STATE_BYTES) -> dict | None:
    """The saved state, or None when there is none.

    Raises
    ------
    StateReset
        The file holds ``null``.
    InputDataError
        The file cannot be read or breaks a rule of the module notes (one line naming the file).
    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        with open(path, "rb") as fh:
            raw = fh.read(max_bytes + 1)  # never more than the limit, whatever the file's size
        if len(raw) > max_bytes:
            raise ValueError(f"larger than the limit of {max_bytes} bytes")
        doc = json.loads(raw.decode("utf-8"), object_pairs_hook=_unique_keys)
        if doc is None:
            raise StateReset(f"{path}: the saved state is null: starting afresh")
        if not isinstance(doc, dict):
            raise ValueError(f"expected a JSON object at the top level, but got a JSON {type(doc).__name__}")
        return _revive(doc)
    except StateReset:
        raise
    except UnicodeDecodeError as err:
        raise InputDataError(f"{path}: cannot read saved state: not UTF-8 text (byte {err.start})") from err
    except RecursionError as err:
        raise InputDataError(f"{path}: cannot read saved state: nested too deep") from err
    except (OSError, ValueError) as err:
        raise InputDataError(f"{path}: cannot read saved state: {err}") from err


def keep_rejected(path: str | Path, keep: int = KEEP_REJECTED) -> Path | None:
    """Move a rejected state file aside to ``<name>.bad-<UTC time>`` (older ones beyond ``keep`` removed).

    Returns the new name, or None when the file could not be moved (it is then left in place).
    """
    path = Path(path)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target = path.with_name(f"{path.name}.bad-{stamp}")
    n = 1
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.bad-{stamp}-{n}")
    try:
        os.replace(path, target)
    except OSError:
        return None
    old = sorted(path.parent.glob(f"{path.name}.bad-*"), key=lambda p: p.stat().st_mtime, reverse=True)
    for p in old[keep:]:
        try:
            p.unlink()
        except OSError:
            pass
    return target
