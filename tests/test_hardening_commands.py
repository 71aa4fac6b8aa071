"""Commands from the bus: freshness that no replay satisfies, authentication, policy, all counted and logged.

The replays are of frames captured on a bus from ``online-id relearn`` itself, sent again to the service at
later times (75 s, a day) and after a restart; the forgeries are what a node with the DBC but without the
key can build (it reads the freshness value, computes the CRC, guesses the MAC).
"""

import dataclasses
import io
import os
import threading
import time

import pytest

from online_id.service.assembly import SampleAssembler
from online_id.cli import main
from online_id.service.commands import FRESHNESS_FILE, MAC_FAILURES_MAX, keep_freshness
from online_id.config import CommandSettings, MappingSettings, Settings, load_config
from online_id.errors import ConfigError
from online_id.io.bus import CanBus
from online_id.io.dbc import BenchCommand, encode_command, encode_inputs, load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.service.offload import InlineWorker
from online_id.records import FrameFault, SignalSample
from online_id.service.runtime import Runtime, role_mapping
from online_id.service.live import Service

DB = load_dbc(None)
ENC = OutputEncoder(DB)
KEY_HEX = "6b" * 16 + "a1" * 16  # 32 bytes
T0 = 1_790_000_000.0  # a Unix time, as the kernel stamps frames


def _cmd(command, freshness, key=None, crc=True):
    ident, data = encode_command(DB, "OidCommand", "Command", command, freshness, key=key)
    if not crc:
        data = data[:7] + bytes([data[7] ^ 0x5A])
    return ident, data


def _learned(rt):
    b = rt.pipeline.baseline
    for _ in range(5):
        b.learn(speed_rpm=1500.0, f0_hz=25.0, zeta=0.05, load_nm=10.0)
    assert b.bands
    return rt


def _key_file(tmp_path, text=KEY_HEX):
    path = tmp_path / "command-key"
    path.write_text(text + "\n")
    return path


def _runtime(tmp_path=None, key=False, **commands):
    if key:
        commands["key_file"] = str(_key_file(tmp_path))
    return _learned(Runtime(Settings(commands=CommandSettings(**commands))))


def _freshness(rt, t_s):
    """What a sender reads: the answer to a NONE request."""
    (out,) = rt.on_frame(t_s, *_cmd(BenchCommand.NONE, 0))
    values = ENC.decode(*out)
    return int(values["FreshnessValue"]), bool(values["Authenticated"])


# --- the service side ------------------------------------------------------------------------------


def test_the_freshness_value_starts_above_the_clock_and_only_grows():
    rt = _runtime()
    last, authenticated = _freshness(rt, T0)
    assert last == int(T0) and not authenticated
    rt.on_frame(T0 + 1, *_cmd(BenchCommand.ACK_ALERT, last + 1))
    assert rt.pipeline.commands == 1 and _freshness(rt, T0 + 2) == (last + 1, False)
    rt.on_frame(T0 + 3, *_cmd(BenchCommand.ACK_ALERT, last + 1))  # the same value again: a replay
    rt.on_frame(T0 + 4, *_cmd(BenchCommand.ACK_ALERT, last))  # an older one
    rt.on_frame(T0 + 5, *_cmd(BenchCommand.ACK_ALERT, last + 70))  # beyond the window
    assert rt.pipeline.commands == 1 and rt.commands.refusals["not fresh"] == 3
    rt.on_frame(T0 + 6, *_cmd(BenchCommand.ACK_ALERT, last + 60))  # a gap within the window is fine
    assert rt.pipeline.commands == 2 and _freshness(rt, T0 + 7)[0] == last + 60
    assert rt.pipeline.counters.faults[FrameFault.COMMAND_REFUSED] == 3  # bad frames, counted


def test_one_relearn_frame_does_not_clear_the_baselines():
    rt = _runtime()
    last, _ = _freshness(rt, T0)
    rt.on_frame(T0 + 1.0, *_cmd(BenchCommand.RELEARN_BASELINE, last + 1))
    assert rt.pipeline.baseline.bands and rt.pipeline.commands == 0
    rt.on_frame(T0 + 3.0, *_cmd(BenchCommand.RELEARN_BASELINE, last + 2))  # too late to confirm: a new first
    assert rt.pipeline.baseline.bands
    rt.on_frame(T0 + 3.4, *_cmd(BenchCommand.RELEARN_BASELINE, last + 3))  # confirmed within 1 s
    assert not rt.pipeline.baseline.bands and rt.pipeline.commands == 1
    log = rt.commands.take_log()
    assert len(log) == 3 and all("120#" in line for line in log)
    assert "awaiting confirmation" in log[0] and "accepted" in log[2]


def test_relearn_disabled_by_config():
    rt = _runtime(relearn="disabled")
    last, _ = _freshness(rt, T0)
    for k in range(4):
        rt.on_frame(T0 + 0.1 * k, *_cmd(BenchCommand.RELEARN_BASELINE, last + 1 + k))
    assert rt.pipeline.baseline.bands and rt.pipeline.commands == 0
    assert rt.commands.refused == 4 and rt.commands.refusals["policy"] == 4
    assert rt.pipeline.counters.faults[FrameFault.COMMAND_REFUSED] == 0  # the policy's: no bad frames
    rt.on_frame(T0 + 2.0, *_cmd(BenchCommand.ACK_ALERT, last + 5))  # other commands still work
    assert rt.pipeline.commands == 1


def test_bad_crc_is_refused():
    rt = _runtime(relearn="allow")
    last, _ = _freshness(rt, T0)
    rt.on_frame(T0, *_cmd(BenchCommand.RELEARN_BASELINE, last + 1, crc=False))
    rt.on_frame(T0, 0x120, bytes([2, 2, 0, 0, 0, 0, 0, 0]))  # a frame of old: no CRC
    assert rt.pipeline.commands == 0 and rt.pipeline.baseline.bands
    assert rt.pipeline.counters.faults[FrameFault.COMMAND_REFUSED] == 2
    assert all("CRC" in line for line in rt.commands.take_log())


def _pair(rt, t_s, key=None):
    """A legitimate RELEARN pair sent at ``t_s`` (freshness read first), as a sender builds it."""
    last, _ = _freshness(rt, t_s)
    return [_cmd(BenchCommand.RELEARN_BASELINE, last + 1 + k, key) for k in range(2)]


@pytest.mark.parametrize("key", [False, True], ids=["plain", "authenticated"])
def test_a_captured_pair_replayed_later_or_after_a_restart_is_refused(tmp_path, key):
    secret = bytes.fromhex(KEY_HEX) if key else None
    state = tmp_path / "state"
    state.mkdir()
    say = []
    rt = _runtime(tmp_path, key)
    keep_freshness(rt.commands, state / FRESHNESS_FILE, say.append)
    first = _pair(rt, T0, secret)
    rt.on_frame(T0 + 0.1, *first[0])
    rt.on_frame(T0 + 0.3, *first[1])
    assert rt.pipeline.commands == 1 and not rt.pipeline.baseline.bands  # the genuine pair acted
    _learned(rt)
    for later in (0.5, 75.0, 3600.0, 86400.0 * 30):  # the same pair, 0.5 s to a month later
        rt.on_frame(T0 + later, *first[0])
        rt.on_frame(T0 + later + 0.2, *first[1])
    assert rt.pipeline.commands == 1 and rt.pipeline.baseline.bands
    assert rt.commands.refusals["not fresh"] == 8
    second = _pair(rt, T0 + 100.0, secret)  # a newer pair, captured too, but never delivered (jammed)
    for restart in range(2):  # a restart (the value from the disk), and one without the disk (the clock)
        again = _runtime(tmp_path, key)
        if restart == 0:
            keep_freshness(again.commands, state / FRESHNESS_FILE, say.append)
        for frames in (first, second):
            again.on_frame(T0 + 200.0 + restart, *frames[0])
            again.on_frame(T0 + 200.2 + restart, *frames[1])
        assert again.pipeline.commands == 0 and again.pipeline.baseline.bands
        assert again.commands.refusals["not fresh"] == 4
        fresh = _pair(again, T0 + 300.0, secret)  # the genuine sender still gets through
        again.on_frame(T0 + 300.1, *fresh[0])
        again.on_frame(T0 + 300.3, *fresh[1])
        assert again.pipeline.commands == 1 and not again.pipeline.baseline.bands
    assert not say


def test_a_forged_pair_without_the_key_is_refused_in_authenticated_mode(tmp_path):
    rt = _runtime(tmp_path, key=True)
    last, authenticated = _freshness(rt, T0)
    assert authenticated
    wrong = bytes.fromhex("11" * 32)
    for k, key in enumerate((None, wrong)):  # no MAC at all, and a MAC with another key
        rt.on_frame(T0 + k, *_cmd(BenchCommand.RELEARN_BASELINE, last + 1, key))
        rt.on_frame(T0 + k + 0.2, *_cmd(BenchCommand.RELEARN_BASELINE, last + 2, key))
    assert rt.pipeline.commands == 0 and rt.pipeline.baseline.bands
    assert rt.commands.refusals["wrong MAC"] == 4 and rt.commands.awaiting == 0
    log = rt.commands.take_log()
    assert len(log) == 4 and all("refused: its MAC does not match" in line for line in log)
    # guessing: after MAC_FAILURES_MAX wrong MACs within a minute every command is refused, the right one too
    for k in range(MAC_FAILURES_MAX):
        rt.on_frame(T0 + 5 + 0.01 * k, *_cmd(BenchCommand.ACK_ALERT, last + 1, wrong))
    rt.on_frame(T0 + 6, *_cmd(BenchCommand.ACK_ALERT, last + 1, bytes.fromhex(KEY_HEX)))
    assert rt.pipeline.commands == 0 and rt.commands.refusals["wrong MAC"] == MAC_FAILURES_MAX
    assert "wrong MACs within 60 s: every command is refused" in rt.commands.take_log()[-1]
    rt.on_frame(T0 + 70, *_cmd(BenchCommand.ACK_ALERT, last + 1, bytes.fromhex(KEY_HEX)))  # aged out
    assert rt.pipeline.commands == 1


def test_a_forged_pair_with_a_fresh_value_is_accepted_in_plain_mode():
    """Plain mode is what it says: any node can build a valid pair (the service says so at start)."""
    rt = _runtime()
    last, _ = _freshness(rt, T0)
    forged = [(0x120, bytes([2, *(last + 1 + k).to_bytes(4, "little")[:2], 0, 0, 0, 0])) for k in range(2)]
    from online_id.io.crc import crc8_j1850

    for k, (ident, seven) in enumerate(forged):
        rt.on_frame(T0 + 0.1 * k, ident, seven[:7] + bytes([crc8_j1850(seven[:7])]))
    assert rt.pipeline.commands == 1 and not rt.pipeline.baseline.bands


def test_a_value_that_cannot_be_kept_refuses_the_command(tmp_path):
    rt = _runtime()
    blocked = tmp_path / FRESHNESS_FILE
    blocked.mkdir()  # the file's place is taken: it can be neither read nor written (a full or broken disk)
    said = []
    keep_freshness(rt.commands, blocked, said.append)
    last, _ = _freshness(rt, T0)
    rt.on_frame(T0 + 1, *_cmd(BenchCommand.ACK_ALERT, last + 1))
    assert rt.pipeline.commands == 0 and rt.commands.refusals["not kept"] == 1
    assert len(said) == 1 and "cannot read the command freshness" in said[0]
    assert "cannot be kept on disk" in rt.commands.take_log()[-1]


def test_a_kept_value_that_is_no_count_is_said_and_the_clock_used(tmp_path):
    path = tmp_path / FRESHNESS_FILE
    said = []
    for text in ('{"command_freshness": -3}', '{"command_freshness": "x"}', "not json"):
        path.write_text(text)
        rt = _runtime()
        keep_freshness(rt.commands, path, said.append)
        assert _freshness(rt, T0)[0] == int(T0)
    assert len(said) == 3 and all(str(path) in line for line in said)


def test_the_service_says_at_start_whether_commands_are_authenticated(tmp_path, monkeypatch):
    def started(settings):
        log = io.StringIO()
        svc = Service(settings, log=log, worker=InlineWorker(),
                      bus_factory=lambda: CanBus("virtual", f"start-{os.getpid()}"))
        assert svc.run(max_s=0.2) == 0
        lines = [x for x in log.getvalue().splitlines() if "commands are" in x]
        assert len(lines) == 1
        return lines[0]

    line = started(Settings())
    assert "commands are NOT authenticated" in line and "in memory only" in line
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(tmp_path))
    _key_file(tmp_path)
    line = started(Settings(commands=CommandSettings(key_file="command-key"),
                            state=dataclasses.replace(Settings().state, directory=str(tmp_path / "state"))))
    assert "commands are authenticated (HMAC-SHA256" in line and "kept in the state directory" in line


def test_the_service_reports_the_commands_when_it_stops():
    log = io.StringIO()
    svc = Service(Settings(), log=log, worker=InlineWorker(),
                  bus_factory=lambda: CanBus("virtual", f"stop-{os.getpid()}"))
    last, _ = _freshness(svc.runtime, T0)
    for _ in range(2):  # the second is a replay
        svc.runtime.on_frame(T0 + 1, *_cmd(BenchCommand.ACK_ALERT, last + 1))
    assert svc.run(max_s=0.2) == 0
    assert "1 commands accepted, 1 rejected (1 not fresh)" in log.getvalue().splitlines()[-1]


@pytest.mark.parametrize("text,needle", [("zz" * 16, "as hex digits"), ("ab" * 8 + "a", "as hex digits"),
                                         ("ab" * 15, "a key of 15 bytes")])
def test_a_bad_key_file_is_one_line(tmp_path, text, needle):
    _key_file(tmp_path, text)
    with pytest.raises(ConfigError, match=f"commands.key_file: .*command-key.* {needle}"):
        Runtime(Settings(commands=CommandSettings(key_file=str(tmp_path / "command-key"))))
    with pytest.raises(ConfigError, match="commands.key_file: cannot read the key"):
        Runtime(Settings(commands=CommandSettings(key_file=str(tmp_path / "none"))))


def test_the_service_logs_every_command_with_its_frame():
    log = io.StringIO()
    svc = Service(Settings(), log=log, worker=InlineWorker())
    last, _ = _freshness(svc.runtime, T0)
    frame = _cmd(BenchCommand.ACK_ALERT, last + 1)
    svc.runtime.on_frame(T0, *frame)
    svc.runtime.on_frame(T0 + 0.1, *frame)
    svc._report_state()
    lines = [line for line in log.getvalue().splitlines() if "command ACK" in line]
    assert len(lines) == 2 and all(f"120#{frame[1].hex().upper()}" in line for line in lines)
    assert "accepted" in lines[0] and "refused: its freshness is not new" in lines[1]


def test_command_setting_is_validated(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("commands: {relearn: sometimes}\n")
    with pytest.raises(ConfigError, match="commands.relearn"):
        load_config(cfg)


# --- the senders: online-id ack / relearn on a bus, and replays of what they sent -------------------


def _serve(channel, rt, stop, ready, captured):
    """The service's runtime answering on a virtual bus (frames stamped with the wall clock, as the kernel
    does); every command frame it receives is captured, as a node listening on the bus would."""
    with CanBus("virtual", channel) as bus:
        ready.set()
        while not stop.is_set():
            f = bus.recv(0.05)
            if f is None:
                continue
            if f.arbitration_id == 0x120 and f.data[0] != 0:
                captured.append((f.arbitration_id, bytes(f.data)))
            for ident, data in rt.on_frame(time.time(), f.arbitration_id, f.data):
                bus.send(ident, data)


@pytest.mark.parametrize("key", [False, True], ids=["plain", "authenticated"])
def test_ack_and_relearn_build_valid_frames_and_their_replay_is_refused(tmp_path, capsys, key):
    rt = _runtime(tmp_path, key)
    channel = f"fresh-{os.getpid()}-{key}"
    stop, ready, captured = threading.Event(), threading.Event(), []
    thread = threading.Thread(target=_serve, args=(channel, rt, stop, ready, captured))
    thread.start()
    argv = ["--interface", "virtual", "--channel", channel] + (["--key-file", str(_key_file(tmp_path))] if key
                                                                else [])
    try:
        assert ready.wait(10)
        assert main(["ack", *argv]) == 0
        assert "service answered: ACK_ALERT ACCEPTED" in capsys.readouterr().out
        assert main(["relearn", *argv]) == 0
        assert "service answered: RELEARN_BASELINE ACCEPTED" in capsys.readouterr().out
        if key:  # the service expects a MAC: without the key the sender says what to give
            assert main(["ack", "--interface", "virtual", "--channel", channel]) == 2
            assert "give --key-file FILE" in capsys.readouterr().err
    finally:
        stop.set()
        thread.join()
    assert rt.pipeline.commands == 2 and not rt.pipeline.baseline.bands and len(captured) == 3
    _learned(rt)
    pair = captured[1:]
    for later in (75.0, 86400.0):  # the captured RELEARN pair, sent again 75 s and a day later
        for k, (ident, data) in enumerate(pair):
            rt.on_frame(time.time() + later + 0.2 * k, ident, data)
    assert rt.pipeline.commands == 2 and rt.pipeline.baseline.bands
    assert rt.commands.refusals["not fresh"] == 4


# --- inputs ------------------------------------------------------------------------------------------


def _crc_settings():
    m = MappingSettings()
    return Settings(mapping=dataclasses.replace(
        m, **{r: dataclasses.replace(getattr(m, r), crc=f"{getattr(m, r).message}CRC")
              for r in ("dyno_speed", "engine_speed", "dyno_torque")}))


def test_optional_input_crc_is_checked_when_mapped():
    s = _crc_settings()
    frames = encode_inputs([0.0, 0.001, 0.002], [1500.0] * 3, [1500.0] * 3, [10.0] * 3, db=DB,
                           mapping=role_mapping(s.mapping))
    rt = Runtime(s)
    for t, i, d in frames:
        rt.on_frame(t, i, d)
    assert rt.pipeline.counters.bad_frames == 0
    t, i, d = frames[0]
    rt.on_frame(0.003, i, bytes([d[0] ^ 1]) + d[1:])  # one bit flipped: was taken as data
    assert rt.pipeline.counters.faults[FrameFault.BAD_CRC] == 1
    assert "CRC" in rt.decoder.last_fault
    plain = Runtime(Settings())  # not mapped: not checked (benches that cannot send it)
    plain.on_frame(0.0, i, bytes([d[0] ^ 1]) + d[1:])
    assert plain.pipeline.counters.bad_frames == 0


def test_one_wrong_counter_is_one_jump_not_254_missing_frames():
    asm = SampleAssembler(1000.0, 0.2)
    for k in range(200):
        for r in ("dyno_speed", "engine_speed", "dyno_torque"):
            counter = k % 256
            if k == 100 and r == "dyno_torque":
                counter = 98  # one wrong value (behind by one)
            asm.push(SignalSample(r, 1.0, k / 1000.0, counter))
    assert asm.counters.faults[FrameFault.COUNTER_JUMP] == 1  # was: 2 jumps, 255 missing frames
    assert asm.counters.missing_frames == 0


def test_real_losses_are_still_counted_and_a_restarted_sender_resyncs():
    asm = SampleAssembler(1000.0, 0.2)
    k_lost = set(range(50, 55))
    for k in range(300):
        if k in k_lost:
            continue
        counter = k % 256 if k < 200 else (k - 200 + 17) % 256  # the sender restarts its counter at 200
        for r in ("dyno_speed", "engine_speed", "dyno_torque"):
            asm.push(SignalSample(r, 1.0, k / 1000.0, counter))
    assert asm.counters.missing_frames == 3 * 5
    assert asm.counters.faults[FrameFault.COUNTER_JUMP] == 3 + 3  # the loss, and the restart, once per role
    assert asm.counters.samples > 280
