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
from online_id.records import ServiceState
from online_id.service import Service


class _Quiet:
    """Collects the service's log lines so the live view can show them in place."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, text: str) -> None:
        if text.strip():
            self.lines.append(text.strip())

    def flush(self) -> None:
        pass


def _send_paced(bus: CanBus, frames: list, speed: float, done: threading.Event) -> None:
    t_first = frames[0][0]
    wall0 = time.monotonic()
    try:
        for t_s, ident, data in frames:
            delay = (t_s - t_first) / speed - (time.monotonic() - wall0)
            if delay > 0.002:
                time.sleep(delay)
            bus.send(ident, data, t_s=t_s)
    except BusError:
        pass
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
    svc_thread = threading.Thread(target=service.run, name="service", daemon=True)
    svc_thread.start()
    time.sleep(0.2)
    send_thread = threading.Thread(target=_send_paced, args=(sender, frames, args.speed, done), daemon=True)
    send_thread.start()

    latest: dict[str, float] = {}
    bad_crc = 0
    published = 0
    print(f"{'bench time':>10}  {'state':<14} {'f0 [Hz]':>8} {'zeta':>7} {'c_s [Nm/rad]':>12} "
          f"{'d_s':>6} {'frames out':>10}")
    next_row = time.monotonic() + 1.0
    t_sim = 0.0
    shown = 0
    finished_at = None
    while True:
        if done.is_set() and finished_at is None:
            finished_at = time.monotonic()
        if finished_at is not None and (service.runtime.frames_in >= len(frames)
                                        or time.monotonic() > finished_at + 30.0):
            break  # the bench ended and the service has seen every frame: stop it (as SIGTERM would)
        frame = monitor.recv(0.02)
        if frame is not None:
            if frame.arbitration_id in (0x101, 0x102, 0x103):
                t_sim = frame.t_s
            elif encoder.verify(frame.arbitration_id, frame.data):
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
            print(f"{t_sim:9.1f}s  {state:<14} {f0} {zeta} {cs if cs else float('nan'):12.0f} "
                  f"{latest.get('ShaftDamping', math.nan):6.2f} {published:10d}", flush=True)
    service.request_stop()
    svc_thread.join(timeout=10)
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
    print(f"\nFiles: {out_dir}/service-result.json, bench.truth.json")
    return 0 if d.get("valid") else 1
