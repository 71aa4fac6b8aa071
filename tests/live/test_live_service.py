"""The service as a bench runs it: its own process, a kernel socket with a finite buffer, fed at real time.

``online-id run`` is started as a separate process on python-can's
``udp_multicast`` interface (kernel UDP sockets: frames that arrive while
the process is busy wait in its receive buffer and are dropped when it is
full, as on SocketCAN).  Another process sends a simulated bench at real
time (1 kHz samples, 3 frames each); this process listens to what the
service publishes.  Window refits run every second all through the run,
physical fits and state saves too.
"""

from __future__ import annotations

import numpy as np
import pytest

from harness import live_config, live_plant, run_live
from online_id.bench.simulate import simulate_bench
from online_id.config import Settings
from online_id.io.dbc import encode_inputs, load_dbc

pytestmark = pytest.mark.live

GROUP = "239.74.163.17"  # an administratively scoped IPv4 multicast group (TTL 1: this machine only)


def test_service_process_keeps_up_at_real_time_on_a_kernel_socket(tmp_path) -> None:
    seed = 11
    record = simulate_bench(live_plant(seed))
    truth = record.truth
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=load_dbc(None))
    run = run_live(frames, live_config(truth, tmp_path / "state"), tmp_path, GROUP)
    assert run.returncode == 0 and run.counts, run.text
    assert run.sent == len(frames)
    n = run.counts
    # no frame lost: every frame sent was taken (the service's own frames come back as "foreign"), the kernel
    # dropped none, the assembler missed none and found none bad
    assert n["frames_in"] - n["foreign"] == len(frames), run.text
    assert n["dropped"] == 0 and n["missing"] == 0 and n["bad"] == 0, run.text
    # and the samples of the whole stream were made: the grid runs on the kernel's arrival stamps, so a
    # sender that started late and caught up (a loaded machine) shortens the stream by a few milliseconds,
    # and the last samples wait for a next frame that never comes (seen: 5 of 73,000). The arrival stamps
    # are the kernel's, so only the bench can leave a gap in them: a sender paused longer than the input
    # timeout (a load spike on a 2-core machine) is a bench gone silent, whose input timeout and lost
    # samples are right; the service stalling shows in its waiting time, never as a gap
    fs = 1.0 / float(np.median(np.diff(record.time_s)))
    silent = run.sender_max_gap_s > Settings().input.timeout_s
    why = f"{run.text}\nsender's longest pause between two frames: {run.sender_max_gap_s * 1e3:.1f} ms"
    assert n["samples"] >= len(record.time_s) * 0.9995 - (run.sender_max_gap_s * fs if silent else 0.0), why
    # the only input timeout is the end of the bench (after its last sample), never one in the middle
    # unless the sender went silent
    timeouts = [ln for ln in run.log if "state INPUT_TIMEOUT" in ln]
    assert silent or all(f"{n['samples']} samples" in ln for ln in timeouts), why
    # valid within 15 s of the first steady point (the bench starts on it), and right
    valid = [(t, d) for t, _p, d, _k in run.estimates if d.get("Valid")]
    assert valid, "no valid estimate published:\n" + run.text
    assert valid[0][0] - run.t_bench0 <= 15.0, f"first valid estimate {valid[0][0] - run.t_bench0:.1f} s after start"
    f0 = float(np.median([d["ResonanceFreq"] for _t, d in valid[-50:]]))
    assert abs(f0 / truth["f0_hz"] - 1) < 0.01, (f0, truth["f0_hz"])
    assert (tmp_path / "state" / "online-id-state.json").is_file()
