"""State that is corrupt: validated as a whole, all or nothing, kept aside when rejected (issue 16, part 2)."""

import dataclasses
import io
import json
import os
import resource
import time

import numpy as np
import pytest

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.config import Settings, StateSettings
from online_id.errors import InputDataError
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.io.statefile import MAX_STATE_BYTES, StateReset, load_state, save_state
from online_id.service.offload import InlineWorker
from online_id.service.restore import restore_pipeline
from online_id.service.runtime import Runtime
from online_id.service.live import STATE_FILE, Service


@pytest.fixture(scope="module")
def good_state():
    """The saved state of a pipeline that ran 12 s on a simulated bench (a learned estimator)."""
    sc = dataclasses.replace(BenchScenario(), seed=2, operating_points=(OperatingPoint(1200.0, 12.0),))
    rec = simulate_bench(sc)
    rt = Runtime(Settings())
    for t, i, d in encode_inputs(rec.time_s, rec.dyno_speed_rpm, rec.engine_speed_rpm, rec.dyno_torque_nm,
                                 db=load_dbc()):
        rt.on_frame(t, i, d)
    assert rt.pipeline.estimate.valid
    return rt.pipeline.get_state()


def _service(tmp_path, text=None, state=None):
    path = tmp_path / STATE_FILE
    if text is not None:
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
    if state is not None:
        save_state(path, state)
    log = io.StringIO()
    # the restore is the subject, not the worker: an inline one (no child process to spawn and warm up)
    svc = Service(Settings(state=StateSettings(directory=str(tmp_path))), log=log, worker=InlineWorker())
    return svc, log.getvalue()


def _rejected(tmp_path):
    return sorted(p.name for p in tmp_path.glob(f"{STATE_FILE}.bad-*"))


def _fresh(svc):
    return not np.any(svc.runtime.pipeline.estimator.rels.theta)


@pytest.mark.parametrize("text", ["[]", "42", '"x"', "{}", "true", '{"version": 1}', "{not json",
                                  b"\xff\xfe\x00binary", "[" * 100_000, '{"a": 1, "a": 2}'])
def test_malformed_state_files_are_rejected_kept_aside_and_never_fatal(tmp_path, text):
    svc, log = _service(tmp_path, text)  # was: AttributeError: 'list' object has no attribute 'get'
    assert _fresh(svc)
    assert "ignoring saved state" in log and "Traceback" not in log and len(log.strip().splitlines()) == 1
    assert len(_rejected(tmp_path)) == 1 and not (tmp_path / STATE_FILE).exists()


def _broken(state, key, value):
    bad = json.loads(json.dumps(state, default=lambda o: o.tolist()))  # a plain copy
    node = bad
    *path, last = key.split(".")
    for k in path:
        node = node[k]
    node[last] = value
    return bad


@pytest.mark.parametrize("key,value", [
    ("baseline", []), ("detector", "x"), ("tracker", 42), ("estimator", []), ("alerts", {}),
    ("references", {"5": [1.0, 2.0]}),  # was: dropped silently, the rest restored
    ("windows", {"5": [{"y": "AAAA", "u": "AAAA", "solution": [1.0], "speed_rpm": 1.0, "load_nm": 0.0, "t_s": 0}]}),
    ("windows", {"5": {}}), ("windows", {"x": []}), ("windows", []),
    ("healthy_rpm", "fast"),
    ("estimator.rels.P", {"__array__": [[1, 2], [3, 4]], "dtype": "float64"}),  # wrong shape
    ("estimator.rels.theta", {"__array__": [1, 2, 3], "dtype": "object"}),  # was: accepted by the loader
    ("alerts", [{"t_s": 1.0}]),
    ("unknown_key", 1),
])
def test_partly_bad_state_is_rejected_as_a_whole(tmp_path, good_state, key, value):
    svc, log = _service(tmp_path, json.dumps(_broken(good_state, key, value)))
    assert _fresh(svc), "some of a rejected state was used"
    assert "ignoring saved state" in log and any(part in log for part in key.split("."))
    assert len(_rejected(tmp_path)) == 1


def test_good_state_is_restored_whole(tmp_path, good_state):
    svc, log = _service(tmp_path, state=good_state)
    assert "restored estimator state" in log and not _rejected(tmp_path)
    assert np.array_equal(svc.runtime.pipeline.estimator.rels.theta, good_state["estimator"]["rels"]["theta"])


def test_a_state_of_the_release_before_learned_from_windows_is_restored(tmp_path, good_state):
    older = {k: v for k, v in good_state.items() if k != "windows"}
    svc, log = _service(tmp_path, state=older)
    assert "restored estimator state" in log and not _rejected(tmp_path)
    assert not _fresh(svc) and svc.runtime.pipeline.get_state()["windows"] == {}


def test_null_is_a_reported_reset(tmp_path):
    svc, log = _service(tmp_path, "null")  # was: ignored silently
    assert _fresh(svc) and "null" in log and "reset" in log
    with pytest.raises(StateReset):
        load_state(tmp_path / STATE_FILE)


def test_huge_state_file_is_refused_without_reading_it(tmp_path):
    path = tmp_path / STATE_FILE
    with open(path, "wb") as fh:
        fh.truncate(1 << 30)  # 1 GiB (sparse): was read whole (2.27 GB RSS) and accepted
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.monotonic()
    with pytest.raises(InputDataError, match="larger than the limit"):
        load_state(path)
    assert time.monotonic() - t0 < 5.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 2 * MAX_STATE_BYTES // 1024 + 50_000
    svc, log = _service(tmp_path)
    assert _fresh(svc) and "larger than the limit" in log and len(_rejected(tmp_path)) == 1


def test_rejected_files_are_kept_up_to_a_limit(tmp_path):
    for k in range(8):
        _service(tmp_path, f"[{k}]")
        assert not (tmp_path / STATE_FILE).exists()
    assert 1 <= len(_rejected(tmp_path)) <= 5


def test_restore_reports_and_never_raises(tmp_path):
    msgs = []
    (tmp_path / "s.json").write_text("[]")
    assert restore_pipeline(tmp_path / "s.json", Settings(), msgs.append) is None
    assert len(msgs) == 1 and "expected a JSON object" in msgs[0]


def test_save_is_atomic_when_the_write_fails(tmp_path, good_state, monkeypatch):
    path = tmp_path / STATE_FILE
    save_state(path, good_state)
    before = path.read_bytes()

    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError):
        save_state(path, good_state | {"healthy_rpm": 1.0})
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [STATE_FILE]


def _canonical(doc) -> str:
    return json.dumps(doc, sort_keys=True, default=lambda x: np.asarray(x).tolist())


def _spoil(doc) -> None:
    """Change every list, dict and array in ``doc`` in place, as a caller editing its copy would."""
    if isinstance(doc, dict):
        for v in doc.values():
            _spoil(v)
        doc["spoiled"] = True
    elif isinstance(doc, list):
        for v in doc:
            _spoil(v)
        doc.append("spoiled")
    elif isinstance(doc, np.ndarray) and doc.flags.writeable and doc.dtype.kind in "fiu":
        doc[...] = 7


def test_a_saved_state_is_the_callers_own(good_state):
    """A state document handed out (to be saved, edited, loaded elsewhere) shares nothing with the running
    pipeline: changing it in place changes neither the pipeline nor the next document (a frozen reference
    handed out live was scaled twice by a caller that edited two documents)."""
    rt = Runtime(Settings())
    rt.pipeline.load_state(good_state)
    base = rt.pipeline.policy.baseline
    for k in range(12):  # learned cells with frozen references, and a backlash finding
        base.learn(speed_rpm=1200.0, f0_hz=20.0 + 0.01 * k, zeta=0.05, load_nm=0.0)
    base.backlash = {"speed_rpm": 1200.0, "shift_pct": 3.0}
    first = rt.pipeline.get_state()
    before = _canonical(first)
    assert any(c[10] for cells in first["baseline"]["bands"].values() for c in cells)
    _spoil(first)
    assert _canonical(rt.pipeline.get_state()) == before
