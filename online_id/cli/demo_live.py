"""The live part of ``online-id demo``: simulator -> virtual CAN bus -> service -> consumer."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import threading
import time
from pathlib import Path

from online_id.bench.scenario import BenchScenario
from online_id.bench.simulate import simulate_bench
from online_id.config import BusSettings, InertiaSettings, ModelSettings, Settings
from online_id.errors import BusError, DbcError
from online_id.io.bus import CanBus
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.io.player import send_paced
from online_id.records import ServiceState
from online_id.service.live import Service


STALL_S = 120.0  # the demo gives up when its service takes no frame for this long (however slow the machine)
LAG_STREAM_S = 3.0
"""The bench is sent at real time instead of ``--speed`` while the service's slow work (refits, checks) has a
job in flight for longer than this much stream time: at 40x real time a refit needs 40x the CPU it needs on a
bench, which a busy machine does not give, and the estimate would then depend on the machine, not the data."""


class _Quiet:
    """Collects the service's log lines so the live view can show them in place."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, text: str) -> None:
        if text.strip():
            self.lines.append(text.strip())

    def flush(self) -> None:
        pass


def _send(bus: CanBus, frames: list, speed: float, done: threading.Event, failed: list[str],
          slow_down=None) -> None:
    try:
        send_paced(bus, frames, speed=speed, slow_down=slow_down)
    except BusError as err:
        failed.append(str(err))
    finally:
        done.set()


def run_live(args: argparse.Namespace) -> int:
    scenario = dataclasses.replace(BenchScenario(), seed=args.seed)
    record = simulate_bench(scenario)
    truth = record.truth
    print(f"Simulated bench: {truth['duration_s']:.0f} s at {truth['fs_hz']:g} Hz, J1 {truth['J1']:g} / J2 "
          f"{truth['J2']:g} kg m^2, c_s {truth['c_s']:g} Nm/rad, d_s {truth['d_s']:g} Nms/rad, "
          f"{truth['n_cyl']} cylinders; true resonance {truth['f0_hz']:.3f} Hz, damping {truth['zeta']:.4f}")
    db = load_dbc(None)
    frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                           db=db)
    channel = f"online-id-demo-{os.getpid()}"
    settings = Settings(
        bus=BusSettings(interface="virtual", channel=channel),
        inertias=InertiaSettings(J1=truth["J1"]),
        model=dataclasses.replace(ModelSettings(), pulses_per_rev=truth["pulses_per_rev"]),
    )
    print(f"Sending {len(frames)} frames on the virtual CAN bus '{channel}' at {args.speed:g}x real time "
          f"(about {truth['duration_s'] / args.speed:.0f} s); the service runs on the same bus with "
          f"J1 = {truth['J1']:g} kg m^2 from the dyno data sheet.\n")
    log = _Quiet()

    def open_service_bus() -> CanBus:
        return CanBus("virtual", channel, preserve_timestamps=True)

    service = Service(settings, log=log, bus_factory=open_service_bus)
    monitor = CanBus("virtual", channel)
    sender = CanBus("virtual", channel, preserve_timestamps=True)
    encoder = OutputEncoder(db)
    done = threading.Event()
    send_failed: list[str] = []
    svc_thread = threading.Thread(target=service.run, name="service", daemon=True)
    svc_thread.start()
    time.sleep(0.2)
    slowed = [0]

    def slow_down() -> bool:  # backpressure (see LAG_STREAM_S); counted in checks of 300 frames (0.1 s of stream)
        behind = service.runtime.pipeline.slow_work_lag_s > LAG_STREAM_S
        slowed[0] += behind
        return behind

    send_thread = threading.Thread(target=_send, args=(sender, frames, args.speed, done, send_failed, slow_down),
                                   daemon=True)
    send_thread.start()

    latest: dict[str, float] = {}
    bad_crc = 0
    published = 0
    print(f"{'service t':>10}  {'state':<14} {'f0 [Hz]':>8} {'zeta':>7} {'c_s [Nm/rad]':>12} "
          f"{'d_s':>6} {'frames out':>10}")
    next_row = time.monotonic() + 1.0
    shown = 0
    progress = (0, time.monotonic())  # frames the service had taken, and when that count last grew
    stalled = ""
    pipeline = service.runtime.pipeline
    while True:
        taken = service.runtime.frames_in
        if taken > progress[0]:
            progress = (taken, time.monotonic())
        if done.is_set() and taken >= len(frames):
            break  # the bench ended and the service has taken every frame: stop it (as SIGTERM would)
        if not svc_thread.is_alive():
            stalled = "the service ended before it had taken every frame"
            break
        if time.monotonic() - progress[1] > STALL_S:
            stalled = f"the service took no frame for {STALL_S:g} s"
            break
        frame = monitor.recv(0.02)
        if frame is not None and frame.arbitration_id not in (0x101, 0x102, 0x103):  # not the bench's own
            if encoder.verify(frame.arbitration_id, frame.data):
                published += 1
                try:
                    latest.update(encoder.decode(frame.arbitration_id, frame.data))
                except DbcError:
                    bad_crc += 1
            else:
                bad_crc += 1
        while shown < len(log.lines):
            print(f"{'':>10}  {log.lines[shown]}")
            shown += 1
        if time.monotonic() >= next_row:
            next_row = time.monotonic() + 1.0
            state = ServiceState(int(latest.get("State", 0))).name
            valid = latest.get("Valid", 0)
            f0 = f"{latest.get('ResonanceFreq', math.nan):8.3f}" if valid else f"{'-':>8}"
            zeta = f"{latest.get('DampingRatio', math.nan):7.4f}" if valid else f"{'-':>7}"
            cs = latest.get("ShaftStiffness", 0.0)
            t_service = pipeline.t_s - pipeline.t_first if pipeline.t_first is not None else 0.0
            print(f"{t_service:9.1f}s  {state:<14} {f0} {zeta} {cs if cs else float('nan'):12.0f} "
                  f"{latest.get('ShaftDamping', math.nan):6.2f} {published:10d}", flush=True)
    service.request_stop()
    svc_thread.join(timeout=60)
    for bus in (monitor, sender):
        bus.close()
    result = service.runtime.pipeline.result()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "service-result.json").write_text(json.dumps(result, indent=2))
    (out_dir / "bench.truth.json").write_text(json.dumps(truth, indent=2, default=float))
    d = result["driveline"]
    print(f"\nService stopped: {result['counters']['samples']} samples, {service.runtime.frames_in} frames in, "
          f"{service.runtime.frames_out} frames out ({bad_crc} failed the CRC check at the consumer), "
          f"final state {result['state']}")
    print("\nAgainst the truth")
    print(f"  {'':14} {'truth':>10} {'estimate':>10} {'error':>8}")
    for name, key in (("f0 [Hz]", "f0_hz"), ("zeta", "zeta"), ("c_s [Nm/rad]", "c_s"), ("d_s [Nms/rad]", "d_s")):
        est = d.get(key)
        err = f"{100 * (est - truth[key]) / truth[key]:+7.2f}%" if est is not None else "-"
        print(f"  {name:14} {truth[key]:10.4g} {est if est is not None else float('nan'):10.4g} {err:>8}")
    if slowed[0]:
        print(f"\nThe bench was sent at real time for about {slowed[0] * 0.1:.1f} s of its {truth['duration_s']:.0f} s, "
              f"while the service's refits ran behind the stream (this machine gave them less than "
              f"{args.speed:g}x the CPU a bench needs)")
    print(f"\nFiles: {out_dir}/service-result.json, bench.truth.json")
    why = []
    if send_failed:
        why.append(f"the bench could not send: {send_failed[0]}")
    if stalled:
        why.append(f"{stalled} ({service.runtime.frames_in} of {len(frames)} frames)")
    if not d.get("valid"):
        why.append(f"the service ended in {result['state']} without a valid estimate "
                   f"(last reason: {pipeline.last_estimate.why if pipeline.last_estimate else 'no estimate yet'})")
    if why:
        print("\ndemo FAILED: " + "; ".join(why))
        return 1
    return 0
