"""Does a broker that is down slow the receive loop?  Side by side in one run: broker up, broker down, no MQTT.

Usage::

    python benchmarks/bench_mqtt.py [--seconds S] [--block N] [--buffer N] [--calls N]

Starts a real ``mosquitto`` on a free loopback port (Debian package
mosquitto).  Three runtimes process the same simulated bench (1 kHz samples,
3 frames per sample, publications at 10 Hz), each with its own hook:

* ``up``: :class:`~online_id.io.mqtt.MqttTelemetry` connected to the broker
  (its sender and paho's network threads publish while we measure);
* ``down``: the same, pointed at a loopback port where nothing listens
  (paho retries in its thread; the buffer of ``--buffer`` messages fills,
  then the oldest are dropped);
* ``none``: no telemetry.

Enqueue: the hook alone, ``MqttTelemetry.publish`` with what the pipeline
publishes at each 10 Hz tick (an estimate, a quality, a status), ``--calls``
calls per sink in blocks of 100, the sinks taking turns (order rotating);
between blocks (not timed) the ``up`` sender empties its buffer, as it keeps
up at the service's rates, while the ``down`` buffer fills and then drops
the oldest.

Receive loop: the frames go through ``Runtime.on_frame`` (what the
service's receive loop calls) in blocks of ``--block`` frames, the three
runtimes taking turns block by block (the order rotating), so that they
share whatever else loads the machine; timed per frame (decode, assemble,
estimate, encode, hook: the receive loop's own work) and per hook call,
with ``time.perf_counter_ns``.

Prints the medians and 99th percentiles and the ratios down/up (and
up/none for the frames).  The slow work (refits) runs inline here, which puts
it in the tail of every runtime alike, not in the medians.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_pipeline import machine  # noqa: E402
from mqtt_broker import EXE, MISSING, Mosquitto, free_port, wait_for  # noqa: E402

from online_id.bench import BenchScenario, OperatingPoint, simulate_bench  # noqa: E402
from online_id.config import MqttSettings, Settings  # noqa: E402
from online_id.io.dbc import encode_inputs  # noqa: E402
from online_id.io.mqtt import MqttTelemetry  # noqa: E402
from online_id.service.offload import InlineWorker  # noqa: E402
from online_id.records import EstimateOut, QualityOut, ServiceState, StatusOut  # noqa: E402
from online_id.service.runtime import Runtime  # noqa: E402


class Timed:
    """A hook that times each call of the telemetry's ``publish``."""

    def __init__(self, publish) -> None:
        self.publish, self.ns = publish, []

    def __call__(self, pubs) -> None:
        t0 = time.perf_counter_ns()
        self.publish(pubs)
        self.ns.append(time.perf_counter_ns() - t0)


def stats(ns) -> tuple[float, float]:
    a = np.asarray(ns, dtype=float) / 1e3
    return float(np.median(a)), float(np.percentile(a, 99))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="seconds of simulated bench (default 30)")
    ap.add_argument("--block", type=int, default=300, help="frames per turn (default 300)")
    ap.add_argument("--buffer", type=int, default=1000, help="mqtt.buffer_messages (default 1000)")
    ap.add_argument("--calls", type=int, default=20000, help="enqueue calls per sink (default 20000)")
    args = ap.parse_args(argv)
    if EXE is None:
        print(f"bench_mqtt: {MISSING}", file=sys.stderr)
        return 1
    rec = simulate_bench(dataclasses.replace(BenchScenario(), seed=5,
                                             operating_points=(OperatingPoint(1500.0, args.seconds),)))
    frames = encode_inputs(rec.time_s, rec.dyno_speed_rpm, rec.engine_speed_rpm, rec.dyno_torque_nm)
    with tempfile.TemporaryDirectory() as tmp:
        broker = Mosquitto(Path(tmp)).start()
        try:
            sinks = {
                "up": MqttTelemetry(MqttSettings(host="127.0.0.1", port=broker.port, bench="bench-up",
                                                 buffer_messages=args.buffer), lambda _t: None),
                "down": MqttTelemetry(MqttSettings(host="127.0.0.1", port=free_port(), bench="bench-down",
                                                   buffer_messages=args.buffer, reconnect_max_s=1.0),
                                      lambda _t: None),
            }
            if not wait_for(lambda: sinks["up"].connected, 10):
                print("bench_mqtt: the telemetry did not connect to mosquitto", file=sys.stderr)
                return 1
            tick = [EstimateOut(1.0, 23.4, 0.05, 12000.0, 3.0, True), QualityOut(1.0, 0.004, 2e-5, 14.0, 900),
                    StatusOut(1.0, ServiceState.TRACKING, 0, 0)]
            direct = {name: Timed(sink.publish) for name, sink in sinks.items()}
            for k in range(args.calls // 100):
                for name in (("up", "down") if k % 2 == 0 else ("down", "up")):
                    for _ in range(100):
                        direct[name](tick)
                wait_for(lambda: sinks["up"].idle(), 10)  # not timed: the up sender empties its buffer
            runtimes, hooks, per_frame = {}, {}, {}
            for name in ("up", "down", "none"):
                rt = Runtime(Settings(), worker=InlineWorker())
                rt.pipeline.warm_up()
                if name in sinks:
                    hooks[name] = rt.on_publish = Timed(sinks[name].publish)
                runtimes[name], per_frame[name] = rt, []
            order = list(runtimes)
            for k, start in enumerate(range(0, len(frames), args.block)):
                block = frames[start:start + args.block]
                for name in order[k % 3:] + order[:k % 3]:
                    rt, out = runtimes[name], per_frame[name]
                    for t, ident, data in block:
                        t0 = time.perf_counter_ns()
                        rt.on_frame(t, ident, data)
                        out.append(time.perf_counter_ns() - t0)
            wait_for(lambda: sinks["up"].idle(), 10)
            up, down = sinks["up"], sinks["down"]
            print(f"machine: {machine()}")
            print(f"{len(frames)} frames ({args.seconds:g} s of bench) per runtime, blocks of {args.block}, "
                  f"mosquitto on 127.0.0.1:{broker.port}")
            print(f"up:   {up.enqueued} messages enqueued, {up.published} published, {up.dropped} dropped")
            print(f"down: {down.enqueued} messages enqueued, {down.published} published, {down.dropped} dropped "
                  f"(buffer {args.buffer}); fault: {down.fault}")
            print(f"\n{'':24}{'up':>16}{'down':>16}{'none':>16}{'down/up':>10}")
            (eu, eu99), (ed, ed99) = stats(direct["up"].ns), stats(direct["down"].ns)
            print(f"{'enqueue median [us]':24}{eu:16.2f}{ed:16.2f}{'':>16}{ed / eu:10.2f}")
            print(f"{'enqueue p99 [us]':24}{eu99:16.2f}{ed99:16.2f}{'':>16}{ed99 / eu99:10.2f}")
            (fu, fu99), (fd, fd99), (fn, fn99) = (stats(per_frame[n]) for n in ("up", "down", "none"))
            print(f"{'on_frame median [us]':24}{fu:16.2f}{fd:16.2f}{fn:16.2f}{fd / fu:10.2f}")
            print(f"{'on_frame p99 [us]':24}{fu99:16.2f}{fd99:16.2f}{fn99:16.2f}{fd99 / fu99:10.2f}")
            (hu, _), (hd, _) = stats(hooks["up"].ns), stats(hooks["down"].ns)
            print(f"{'hook in on_frame [us]':24}{hu:16.2f}{hd:16.2f}{'':>16}{hd / hu:10.2f}")
            print(f"(enqueue: {len(direct['up'].ns)} calls of 3 publications per sink; hook in on_frame: "
                  f"{len(hooks['up'].ns)} calls per sink, medians; on_frame up/none median ratio {fu / fn:.2f})")
            for sink in sinks.values():
                sink.close("TRACKING", timeout_s=1.0)
        finally:
            broker.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
