"""CAN logs (.log, .asc, .blf), `cantools decode` on our frames, and `online-id convert`."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from online_id.errors import InputDataError
from online_id.io.canlog import SUFFIXES, read_log, write_log
from online_id.io.dbc import InputDecoder, encode_inputs, load_dbc
from online_id.records import ROLES

REPO_DBC = Path(__file__).resolve().parent.parent / "dbc" / "online_id.dbc"


def _frames(n=600, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(50e-6, 2e-3, n))  # irregular times
    t[0] = 0.0
    frames = []
    for i in range(n):
        length = int(rng.integers(0, 9))
        fid = int(rng.integers(0, 0x800)) if i % 5 else int(rng.integers(0x800, 0x20000000))
        frames.append((float(t[i]), fid, rng.integers(0, 256, length, dtype=np.uint8).tobytes()))
    return frames


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_write_read_round_trip(tmp_path, suffix):
    frames = _frames()
    path = tmp_path / f"bus{suffix}"
    assert write_log(path, frames) == len(frames)
    back = list(read_log(path))
    assert len(back) == len(frames)
    for (t, fid, data), (t2, fid2, data2, ext, err) in zip(frames, back):
        assert (fid2, data2, ext, err) == (fid, data, fid > 0x7FF, False)
        assert abs(t2 - t) <= 0.5e-6 + 1e-9  # .log/.asc keep microseconds, .blf nanoseconds


def test_extended_flag_can_be_given(tmp_path):
    path = tmp_path / "ext.log"
    write_log(path, [(0.0, 0x101, b"\x01", True), (0.001, 0x101, b"\x02")])
    assert [(f[1], f[3]) for f in read_log(path)] == [(0x101, True), (0x101, False)]


def test_bad_suffix_missing_and_corrupt_files(tmp_path):
    for fn in (lambda p: write_log(p, []), lambda p: list(read_log(p))):
        with pytest.raises(InputDataError, match=r"bus\.trc: expected a CAN log with suffix \.log, \.asc, \.blf"):
            fn(tmp_path / "bus.trc")
    with pytest.raises(InputDataError, match=r"nothere\.log: cannot read the CAN log"):
        list(read_log(tmp_path / "nothere.log"))
    log = tmp_path / "bad.log"
    log.write_text("(0.000000) can0 101#0011 R\n\n(0.001000) can0 10Z#00 R\n(0.002000) can0 101#00 R\n")
    with pytest.raises(InputDataError, match=rf"{log}:3: corrupt \.log CAN log"):
        list(read_log(log))
    blf = tmp_path / "bad.blf"
    blf.write_bytes(b"LOGG" + bytes(100))
    with pytest.raises(InputDataError, match=r"bad\.blf"):
        list(read_log(blf))


def test_cantools_decode_reads_our_candump_lines(tmp_path):
    db = load_dbc()
    frames = encode_inputs([0.0], [1234.5678], [-800.25], [-42.5], db=db)
    path = tmp_path / "one.log"
    write_log(path, frames)
    lines = path.read_text()
    assert lines.splitlines()[0].startswith("(0.000000) can0 101#")
    out = subprocess.run([sys.executable, "-m", "cantools", "decode", str(REPO_DBC)], input=lines,
                         capture_output=True, text=True, check=True, timeout=60).stdout
    assert "DynoSpeed(" in out and "DynoSpeed: 1234.5678 rpm" in out
    assert "EngineSpeed: -800.25 rpm" in out and "DynoTorque: -42.5 Nm" in out


def _run_cli(argv):
    from online_id.cli import main

    return main(argv)


def _bench_csv(path, n=400, seed=3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 1000.0
    dyno = 1500 + np.round(rng.normal(0, 3, n), 4)
    engine = 1500 + np.round(rng.normal(0, 3, n), 4)
    torque = np.round(rng.normal(40, 15, n), 4)
    np.savetxt(path, np.column_stack([t, dyno, engine, torque]), fmt=["%.6f", "%.4f", "%.4f", "%.4f"],
               delimiter=",", header="time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm", comments="")
    return t, {"dyno_speed": dyno, "engine_speed": engine, "dyno_torque": torque}


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_convert_csv_replays_to_the_same_samples(tmp_path, capsys, suffix):
    t, cols = _bench_csv(tmp_path / "bench.csv")
    out = tmp_path / f"bench{suffix}"
    assert _run_cli(["convert", str(tmp_path / "bench.csv"), str(out)]) == 0
    assert f"Wrote {3 * t.size} frames" in capsys.readouterr().out
    dec = InputDecoder(load_dbc())
    got = {role: [] for role in ROLES}
    for t_s, fid, data, ext, err in read_log(out):
        for s in dec.decode(fid, data, t_s, ext):
            got[s.role].append((s.t_s, s.value, s.counter))
    for role in ROLES:
        times, values, counters = map(np.array, zip(*got[role]))
        factor = 1.0 if role == "dyno_torque" else math.pi / 30.0
        assert np.allclose(times, t, atol=1e-6, rtol=0)
        assert np.array_equal(np.round(values / factor, 4), cols[role])  # the DBC resolves 1e-4
        assert list(counters) == [i % 256 for i in range(t.size)]


def test_convert_errors(tmp_path, capsys):
    _bench_csv(tmp_path / "bench.csv")
    assert _run_cli(["convert", str(tmp_path / "bench.csv"), str(tmp_path / "bench.txt")]) == 2
    assert "bench.txt: expected a CAN log with suffix" in capsys.readouterr().err
    assert _run_cli(["convert", str(tmp_path / "bench.csv"), str(tmp_path / "b.log"), "--decimate", "x=2"]) == 2
    assert "--decimate: expected ROLE=K" in capsys.readouterr().err
    assert _run_cli(["convert", str(tmp_path / "bench.csv"), str(tmp_path / "b.log"),
                     "--dbc", str(tmp_path / "none.dbc")]) == 2
    assert "none.dbc: cannot read the DBC file" in capsys.readouterr().err


def test_convert_with_rates_and_jitter(tmp_path, capsys):
    t, _ = _bench_csv(tmp_path / "bench.csv")
    out = tmp_path / "bench.blf"
    assert _run_cli(["convert", str(tmp_path / "bench.csv"), str(out), "--decimate", "dyno_torque=4",
                     "--jitter-us", "100"]) == 0
    frames = list(read_log(out))
    assert len(frames) == 2 * t.size + t.size // 4
    times = [f[0] for f in frames]
    assert times == sorted(times)


def test_simulate_writes_a_can_log_matching_the_csv(tmp_path, capsys):
    from online_id.cli import main

    cfg = tmp_path / "short.yaml"
    cfg.write_text("operating_points: [{speed_rpm: 1200, duration_s: 1}]\nseed: 2\n")
    log = tmp_path / "sim.log"
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "sim.csv"), "--can-log", str(log)]) == 0
    assert f"CAN frames to {log}" in capsys.readouterr().out
    csv = np.loadtxt(tmp_path / "sim.csv", delimiter=",", skiprows=1)
    dec = InputDecoder(load_dbc())
    torque = [s.value for f in read_log(log) for s in dec.decode(f[1], f[2], f[0]) if s.role == "dyno_torque"]
    assert np.allclose(torque, csv[:, 3], atol=0.6e-4, rtol=0)
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "x.csv"), "--can-log", "x.trc"]) == 2
    assert "--can-log: expected a file ending in .log" in capsys.readouterr().err
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "none" / "x.csv")]) == 2
    assert "x.csv: cannot write" in capsys.readouterr().err


@pytest.mark.parametrize("seed", [3, 4])
def test_buffered_mf4_writer_writes_what_python_cans_writer_writes(tmp_path, seed):
    """The chunked .mf4 writer (python-can's writes frame by frame, minutes for a minute of bus) reads back
    as python-can's own: standard and extended IDs, 0-8 bytes, channels, directions, an error frame among them."""
    import random

    import can

    from online_id.io.canlog import BufferedMF4Writer

    rng = random.Random(seed)
    msgs, t = [], 1.79e9
    for k in range(1500):
        t += rng.uniform(1e-4, 1e-3)
        ext = k % 5 == 0
        msgs.append(can.Message(timestamp=t, arbitration_id=rng.randrange(1 << 29 if ext else 0x800),
                                is_extended_id=ext, data=bytes(rng.randrange(256) for _ in range(rng.randint(0, 8))),
                                channel=rng.choice([None, 0, 1]), is_rx=bool(k % 3)))
    msgs.insert(rng.randrange(len(msgs)), can.Message(timestamp=msgs[50].timestamp, arbitration_id=5,
                                                      is_error_frame=True))
    BufferedMF4Writer.CHUNK = 400  # several chunks
    try:
        for cls, name in ((can.io.MF4Writer, "ref.mf4"), (BufferedMF4Writer, "ours.mf4")):
            w = cls(tmp_path / name)
            for m in msgs:
                w.on_message_received(m)
            w.stop()
    finally:
        BufferedMF4Writer.CHUNK = 20_000

    def frames(name):
        return sorted((m.timestamp, m.arbitration_id, m.is_extended_id, bytes(m.data), m.is_error_frame, m.channel,
                       m.is_rx, m.dlc) for m in can.io.MF4Reader(tmp_path / name))

    ref = frames("ref.mf4")
    assert len(ref) == len(msgs) and frames("ours.mf4") == ref
