"""Fuzz tier (issue 16, part 6): seeded random and mutated inputs, fast (well under a minute).

Each target gets inputs built from a valid one by random mutation, or made
up from scratch, and must hold its contract: the assembler never raises and
its samples are finite and in order; the state restore never raises and
uses a file whole or not at all; the config loader raises only ConfigError;
the CSV and CAN-log readers raise only InputDataError.  Seeds are fixed, so
a failure reproduces; set ``ONLINE_ID_FUZZ_SEED`` to explore others.
"""

import json
import math
import os

import numpy as np
import pytest

from online_id.service.assembly import SampleAssembler
from online_id.config import Settings, load_config
from online_id.errors import ConfigError, InputDataError
from online_id.io.canlog import read_log, write_log
from online_id.io.statefile import save_state
from online_id.service.pipeline import Pipeline
from online_id.records import ROLES, SignalSample
from online_id.service.restore import restore_pipeline
from online_id.ingest.signals import read_bench_csv

SEED = int(os.environ.get("ONLINE_ID_FUZZ_SEED", "16"))


# --- the assembler ------------------------------------------------------------------------------------


def _times(rng, n):
    """A clock with every fault: jitter, gaps, steps both ways, NaN, inf, huge, outliers."""
    t = np.cumsum(rng.exponential(1e-3 / 3, n))
    for _ in range(rng.integers(0, 4)):
        k = int(rng.integers(0, n))
        t[k:] += rng.choice([-7200.0, -1.0, -0.3, 0.5, 2.0, 7200.0])
    bad = rng.random(n) < 0.01
    t[bad] = rng.choice([math.nan, math.inf, -math.inf, 1e300, -1e300, 0.0, 1e9], int(bad.sum()))
    return t


@pytest.mark.parametrize("case", range(12))
def test_fuzz_assembler(case):
    rng = np.random.default_rng([SEED, case])
    n = 6000
    asm = SampleAssembler(float(rng.choice([100.0, 1000.0])), float(rng.choice([0.05, 0.2])),
                          slow_roles=("engine_speed",) if rng.random() < 0.3 else (),
                          max_jump_s=float(rng.choice([1.0, 5.0])))
    out = []
    for t in _times(rng, n):
        role = ROLES[int(rng.integers(0, 3))]
        counter = int(rng.integers(0, 256)) if rng.random() < 0.05 else None
        out.extend(asm.push(SignalSample(role, float(rng.normal()), float(t), counter)))
        if rng.random() < 0.01:
            out.extend(asm.poll(float(t) + float(rng.choice([0.0, 0.5, 1e6, math.nan]))))
    for a, b in zip(out, out[1:]):
        assert math.isfinite(a.t_s) and (b.t_s > a.t_s or b.discontinuity)
    c = asm.counters
    assert c.samples == len(out) and c.bad_frames + c.samples <= 3 * n + len(out)


# --- the state file --------------------------------------------------------------------------------------


_JUNK = [None, 0, -1, 1e308, "x", [], {}, [1, 2], {"__array__": [1], "dtype": "object"}, True, math.nan,
         {"__array__": [[1, 2], [3]], "dtype": "float64"}, {"a": {"b": []}}]


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict) and "__array__" not in node:  # an array is one node
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list) and len(node) < 50:  # not into the long arrays: their items are all alike
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


def _mutate(doc, rng):
    """A copy of a JSON document with one to three nodes replaced, removed, or added beside."""
    doc = json.loads(json.dumps(doc))
    paths = [p for p in _paths(doc) if p]
    for _ in range(int(rng.integers(1, 4))):
        path = paths[int(rng.integers(len(paths)))]
        parent = doc
        try:
            for k in path[:-1]:
                parent = parent[k]
            r = rng.random()
            if r < 0.3 and isinstance(parent, dict):
                del parent[path[-1]]
            elif r < 0.4 and isinstance(parent, dict):
                parent["extra"] = 1
            else:
                parent[path[-1]] = _JUNK[int(rng.integers(len(_JUNK)))]
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed the way there
    return doc


@pytest.fixture(scope="module")
def saved_state(tmp_path_factory):
    p = Pipeline(Settings())
    t = np.arange(3000) / 1000.0
    for k, tk in enumerate(t):
        for role, v in zip(ROLES, (125.0 + np.sin(150 * tk), 125.0, 20.0 * np.sign(np.sin(40 * tk)))):
            p.on_signal(SignalSample(role, float(v), float(tk)))
    path = tmp_path_factory.mktemp("state") / "s.json"
    save_state(path, p.get_state())
    return json.loads(path.read_text())


@pytest.mark.parametrize("case", range(30))
def test_fuzz_state_restore(tmp_path, saved_state, case):
    rng = np.random.default_rng([SEED, 100 + case])
    path = tmp_path / "state.json"
    if case % 5 == 4:  # bytes: the valid file cut, flipped or garbage
        raw = bytearray(json.dumps(saved_state).encode())
        raw = raw[: int(rng.integers(0, len(raw)))] if case % 2 else raw
        for k in rng.integers(0, max(1, len(raw)), 5):
            if raw:
                raw[int(k) % len(raw)] = int(rng.integers(0, 256))
        path.write_bytes(bytes(raw))
    else:
        path.write_text(json.dumps(_mutate(saved_state, rng)))
    said = []
    restored = restore_pipeline(path, Settings(), said.append)
    assert len(said) == 1  # one line, whatever happened
    if restored is None:
        assert not path.exists() or "null" in said[0]  # kept aside, not left for the next save
    else:
        assert "restored" in said[0]
        restored.get_state()


# --- the config loader -------------------------------------------------------------------------------------

_KEYS = {
    "input": ["sample_rate_hz", "timeout_s", "slow_roles", "max_time_jump_s"],
    "model": ["na", "forgetting", "band_hz", "window_s"],
    "publish": ["rate_hz", "frame_ids"],
    "inertias": ["J1", "J2"],
    "commands": ["relearn", "confirm_s"],
    "mapping": ["dyno_speed", "command_crc"],
    "bogus": ["x"],
}
_VALUES = ["1", "0", "-1", ".inf", "-.inf", ".nan", "1e400", "1.0e+400", "9" * 400, "x", "[]", "{}", "[1, 2]",
           "null", "true", "{OidEstimate: 0x400}", "{Nope: 1}", "confirm", "[dyno_speed]", "'\x1b[31m'",
           "!!python/object:os.system ls", "&a 1", "*a", "{message: X, signal: Y}"]


@pytest.mark.parametrize("case", range(60))
def test_fuzz_config(tmp_path, case):
    rng = np.random.default_rng([SEED, 200 + case])
    lines = []
    for _ in range(int(rng.integers(1, 5))):
        section = list(_KEYS)[int(rng.integers(len(_KEYS)))]
        lines.append(f"{section}:")
        for _ in range(int(rng.integers(1, 3))):
            key = _KEYS[section][int(rng.integers(len(_KEYS[section])))]
            lines.append(f"  {key}: {_VALUES[int(rng.integers(len(_VALUES)))]}")
    text = "\n".join(lines) + "\n"
    if case % 10 == 9:
        raw = bytearray(text.encode())
        raw[int(rng.integers(len(raw)))] = int(rng.integers(0, 256))
        text = raw
    cfg = tmp_path / "c.yaml"
    cfg.write_bytes(text if isinstance(text, (bytes, bytearray)) else text.encode())
    try:
        s = load_config(cfg)
    except ConfigError as err:
        assert "\n" not in str(err).strip() or "invalid YAML" in str(err)
        return
    for section in ("input", "model", "publish", "commands"):
        for v in vars(getattr(s, section)).values():
            if isinstance(v, float):
                assert math.isfinite(v)


# --- the CSV and CAN-log readers -------------------------------------------------------------------------


def _csv_text(rng, n=400):
    t = np.arange(n) / 1000.0
    cols = np.column_stack([t, 1500 + rng.normal(0, 3, n), 1500 + rng.normal(0, 3, n), rng.normal(40, 15, n)])
    body = "\n".join(",".join(f"{x:.4f}" for x in row) for row in cols)
    return ("time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm\n" + body + "\n").encode()


def _mangle(raw: bytes, rng) -> bytes:
    raw = bytearray(raw)
    kind = int(rng.integers(0, 4))
    if kind == 0:  # cut
        return bytes(raw[: int(rng.integers(0, len(raw)))])
    if kind == 1:  # random bytes flipped
        for k in rng.integers(0, len(raw), 20):
            raw[int(k)] = int(rng.integers(0, 256))
        return bytes(raw)
    if kind == 2:  # a block of random bytes inserted
        k = int(rng.integers(0, len(raw)))
        return bytes(raw[:k]) + rng.integers(0, 256, 64, dtype=np.uint8).tobytes() + bytes(raw[k:])
    return rng.integers(0, 256, int(rng.integers(0, 4000)), dtype=np.uint8).tobytes()  # garbage


@pytest.mark.parametrize("case", range(40))
def test_fuzz_csv_reader(tmp_path, case):
    rng = np.random.default_rng([SEED, 300 + case])
    path = tmp_path / "b.csv"
    path.write_bytes(_mangle(_csv_text(rng), rng))
    try:
        data = read_bench_csv(path)
    except InputDataError as err:
        assert str(err).startswith(str(path))
        return
    assert np.all(np.isfinite(data.dyno_torque_nm)) and np.all(np.diff(data.time_s) > 0)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("logs")
    frames = [(1.7e9 + k * 1e-3, 0x101 + k % 3, bytes([k % 256] * 8)) for k in range(600)]
    out = {}
    for suffix in (".log", ".asc", ".blf"):
        write_log(d / f"x{suffix}", frames)
        out[suffix] = (d / f"x{suffix}").read_bytes()
    return out


@pytest.mark.parametrize("case", range(45))
def test_fuzz_log_reader(tmp_path, logs, case):
    rng = np.random.default_rng([SEED, 400 + case])
    suffix = (".log", ".asc", ".blf")[case % 3]
    path = tmp_path / f"b{suffix}"
    path.write_bytes(_mangle(logs[suffix], rng))
    notes = []
    try:
        frames = list(read_log(path, notes.append))
    except InputDataError as err:
        assert str(err).startswith(str(path)) and "\n" not in str(err)
        return
    assert len(frames) <= 600 + 64 and len(notes) <= 1
    for t, ident, data, ext, err in frames:
        assert isinstance(ident, int) and isinstance(data, bytes)
