"""The receive loop's clock and the end of a run: time from bad frames, absurd first stamps, a failed final save,
an output directory that cannot be written.

The loop is the service's own (:meth:`Service.run`) on a scripted bus: frames as a bench sends them, a frame
that lies about its time, then silence, while the loop ticks its stream clock.
"""

import io
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from online_id.service.assembly import SampleAssembler
from online_id.config import Settings, StateSettings
from online_id.io.bus import Frame
from online_id.io.canlog import write_log
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.service.offload import InlineWorker
from online_id.records import ROLES, FrameFault, ServiceState, SignalSample
from online_id.service.live import Service

DB = load_dbc(None)
T0 = 1_790_000_000.0


def _frames(seconds: float, t0: float = T0) -> list[tuple[float, int, bytes]]:
    n = int(seconds * 1000)
    t = np.arange(n) / 1000.0
    rng = np.random.default_rng(1)
    return [(t0 + ts, i, d) for ts, i, d in encode_inputs(
        t, 1500.0 + rng.normal(0, 1, n), 1500.0 + rng.normal(0, 1, n), 30.0 + rng.normal(0, 5, n), db=DB)]


class ScriptBus:
    """A bus that plays a script: frames (as fast as the loop takes them), silences (real time), probes."""

    receive_buffer_bytes = None

    def __init__(self, script, service_ref):
        self.script = list(script)
        self.service = service_ref
        self.silent_until = None
        self.seen = {}

    def recv(self, timeout):
        while self.script:
            item = self.script[0]
            if isinstance(item, tuple) and item[0] == "silence":
                if self.silent_until is None:
                    self.silent_until = time.monotonic() + item[1]
                if time.monotonic() < self.silent_until:
                    time.sleep(min(timeout, self.silent_until - time.monotonic()))
                    return None
                self.silent_until = None
                self.script.pop(0)
                continue
            if isinstance(item, tuple) and item[0] == "probe":
                self.script.pop(0)
                self.seen[item[1]] = self.service[0].runtime.pipeline.state
                continue
            if isinstance(item, tuple) and item[0] == "do":
                self.script.pop(0)
                item[1]()
                continue
            self.script.pop(0)
            return Frame(*item)
        self.service[0].stop_requested = True
        time.sleep(timeout)
        return None

    def send(self, *args, **kwargs):
        pass

    def dropped(self):
        return None

    def close(self):
        pass


def _run(script, settings=None):
    ref = []
    bus = ScriptBus(script, ref)
    log = io.StringIO()
    svc = Service(settings or Settings(), log=log, bus_factory=lambda: bus, worker=InlineWorker())
    ref.append(svc)
    rc = svc.run(max_s=60)
    return svc, bus.seen, rc, log.getvalue()


@pytest.mark.parametrize("bad_dt", [7200.0, 1e300])
def test_the_loop_never_ticks_from_a_frame_judged_bad(bad_dt):
    good = _frames(2.0)
    last_t, ident, data = good[-1]
    script = [*good, ("probe", "before"), (last_t + bad_dt, ident, data), ("silence", 0.12), ("probe", "short"),
              ("silence", 0.4), ("probe", "long")]
    svc, seen, rc, log = _run(script)
    assert rc == 0 and seen["before"] != ServiceState.INPUT_TIMEOUT
    # 0.12 s of silence is within input.timeout_s (0.2 s): was INPUT_TIMEOUT 50 ms after the lying frame
    assert seen["short"] == seen["before"], log
    assert seen["long"] == ServiceState.INPUT_TIMEOUT  # real silence is still a timeout
    assert svc.runtime.pipeline.counters.time_jumps == 0  # held (+2 h) or refused (1e300), never taken


@pytest.mark.parametrize("absurd", [1e300, -1e300, 1e11])
def test_an_absurd_first_stamp_is_a_bad_time_not_a_clock_step(absurd):
    asm = SampleAssembler(1000.0, 0.2)
    asm.push(SignalSample("dyno_speed", 1.0, absurd, 0))
    got = []
    for k in range(300):
        for r in ROLES:
            got += asm.push(SignalSample(r, 1.0 + k, T0 + k / 1000.0, (k + 1) % 256))
    assert asm.counters.faults[FrameFault.BAD_TIME] == 1
    assert asm.counters.time_jumps == 0  # was: a clock step, 6 good frames dropped
    assert asm.counters.faults[FrameFault.TIME_BACKWARDS] == 0
    assert len(got) >= 298


def test_a_failed_final_save_exits_non_zero(tmp_path):
    from online_id.service.live import STATE_FILE

    s = Settings(state=StateSettings(directory=str(tmp_path), save_interval_s=3600.0))
    # once running, the state file's place is taken (a full or broken disk): the last save cannot replace it
    svc, _seen, rc, log = _run([*_frames(0.5), ("do", (tmp_path / STATE_FILE).mkdir)], s)
    assert rc == 1, log  # was 0: systemd never saw that the state on disk is stale
    assert "cannot save state" in log and "exit status 1: the last save of the state failed" in log
    svc, _seen, rc, log = _run(_frames(0.5), Settings(state=StateSettings(directory=str(tmp_path / "ok"))))
    assert rc == 0 and (tmp_path / "ok" / STATE_FILE).exists()


def _replay_state(tmp_path, state):
    log = tmp_path / "bench.log"
    write_log(log, _frames(3.0, 0.0))
    return subprocess.run([sys.executable, "-m", "online_id", "replay", str(log), "--state", str(state)],
                          capture_output=True, text=True, timeout=300)


def test_replay_state_where_it_cannot_be_written_fails_before_the_replay(tmp_path):
    (tmp_path / "notes.txt").write_text("a file, not a directory\n")
    state = tmp_path / "notes.txt" / "state"
    proc = _replay_state(tmp_path, state)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == (f"error: {state}: cannot write the state: {tmp_path / 'notes.txt'} is not "
                                   f"a directory"), proc.stderr
    assert proc.stdout == ""  # was: the whole replay, then "cannot save the state"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only directory")
def test_replay_state_in_a_read_only_directory_fails_before_the_replay(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    os.chmod(state, 0o555)
    proc = _replay_state(tmp_path, state)
    assert proc.returncode == 2 and "is not writable" in proc.stderr and proc.stdout == "", proc.stderr
