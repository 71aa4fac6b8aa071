"""Commands and inputs from the bus (issue 16, parts 3 and 4).

Command frames carry an alive counter and a CRC that are checked; repeats
are refused and counted; a remote relearn needs a confirmation (or is
disabled); every command is logged with its frame.  Inputs may carry a CRC;
a wrong counter is counted once, not as 254 missing frames.
"""

import dataclasses
import io

import pytest

from online_id.assembly import SampleAssembler
from online_id.config import CommandSettings, MappingSettings, RoleSettings, Settings
from online_id.io.dbc import BenchCommand, encode_command, encode_inputs, load_dbc
from online_id.records import FrameFault, SignalSample
from online_id.runtime import Runtime, role_mapping
from online_id.offload import InlineWorker
from online_id.service import Service

DB = load_dbc(None)


def _cmd(command, counter, crc=True):
    ident, data = encode_command(DB, "OidCommand", "Command", command, counter)
    if not crc:
        data = data[:7] + bytes([data[7] ^ 0x5A])
    return ident, data


def _learned(rt):
    b = rt.pipeline.baseline
    for _ in range(5):
        b.learn(speed_rpm=1500.0, f0_hz=25.0, zeta=0.05, load_nm=10.0)
    assert b.bands
    return rt


def _runtime(**commands):
    return _learned(Runtime(Settings(commands=CommandSettings(**commands))))


def test_one_relearn_frame_from_anyone_does_not_clear_the_baselines():
    rt = _runtime()
    rt.on_frame(1.0, *_cmd(BenchCommand.RELEARN_BASELINE, 7))  # was: baselines gone at once
    assert rt.pipeline.baseline.bands and rt.pipeline.commands == 0
    rt.on_frame(3.0, *_cmd(BenchCommand.RELEARN_BASELINE, 8))  # too late to confirm the first: a new first
    assert rt.pipeline.baseline.bands
    rt.on_frame(3.4, *_cmd(BenchCommand.RELEARN_BASELINE, 9))  # confirmed within 1 s
    assert not rt.pipeline.baseline.bands and rt.pipeline.commands == 1
    log = rt.commands.take_log()
    assert len(log) == 3 and all("120#" in line for line in log)
    assert "awaiting confirmation" in log[0] and "accepted" in log[2]


def test_repeated_counter_is_refused_and_counted():
    rt = _runtime(relearn="allow")
    frame = _cmd(BenchCommand.ACK_ALERT, 42)
    rt.on_frame(1.0, *frame)
    rt.on_frame(1.5, *frame)  # the same frame again: was acted on twice
    rt.on_frame(1.6, *_cmd(BenchCommand.RELEARN_BASELINE, 42))  # same counter, other command
    rt.on_frame(1.7, *_cmd(BenchCommand.RELEARN_BASELINE, 40))  # stale counter
    assert rt.pipeline.commands == 1 and rt.pipeline.baseline.bands
    assert rt.pipeline.counters.faults[FrameFault.COMMAND_REFUSED] == 3
    assert rt.pipeline.counters.bad_frames == 3
    rt.on_frame(1.8, *_cmd(BenchCommand.RELEARN_BASELINE, 43))
    assert rt.pipeline.commands == 2 and not rt.pipeline.baseline.bands
    log = rt.commands.take_log()
    assert sum("refused" in line and "repeats or precedes" in line for line in log) == 3


def test_bad_crc_is_refused():
    rt = _runtime(relearn="allow")
    rt.on_frame(1.0, *_cmd(BenchCommand.RELEARN_BASELINE, 1, crc=False))
    rt.on_frame(1.1, 0x120, bytes([2, 2, 0, 0, 0, 0, 0, 0]))  # a frame of old: no CRC
    assert rt.pipeline.commands == 0 and rt.pipeline.baseline.bands
    assert rt.pipeline.counters.faults[FrameFault.COMMAND_REFUSED] == 2
    assert all("CRC" in line for line in rt.commands.take_log())


def test_relearn_disabled_by_config():
    rt = _runtime(relearn="disabled")
    for k in range(4):
        rt.on_frame(1.0 + 0.1 * k, *_cmd(BenchCommand.RELEARN_BASELINE, 10 + k))
    assert rt.pipeline.baseline.bands and rt.pipeline.commands == 0
    assert rt.commands.refused == 4
    rt.on_frame(2.0, *_cmd(BenchCommand.ACK_ALERT, 20))  # other commands still work
    assert rt.pipeline.commands == 1


def test_the_service_logs_every_command_with_its_frame(tmp_path):
    log = io.StringIO()
    svc = Service(Settings(), log=log, worker=InlineWorker())
    svc.runtime.on_frame(1.0, *_cmd(BenchCommand.ACK_ALERT, 3))
    svc.runtime.on_frame(1.1, *_cmd(BenchCommand.ACK_ALERT, 3))
    svc._report_state()
    lines = [line for line in log.getvalue().splitlines() if "command" in line]
    ident, data = _cmd(BenchCommand.ACK_ALERT, 3)
    assert len(lines) == 2 and all(f"120#{data.hex().upper()}" in line for line in lines)
    assert "accepted" in lines[0] and "refused" in lines[1]


def test_command_setting_is_validated(tmp_path):
    from online_id.config import load_config
    from online_id.errors import ConfigError

    cfg = tmp_path / "c.yaml"
    cfg.write_text("commands: {relearn: sometimes}\n")
    with pytest.raises(ConfigError, match="commands.relearn"):
        load_config(cfg)


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
