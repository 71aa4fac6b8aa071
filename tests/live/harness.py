"""Run ``online-id run`` as its own process on a kernel socket bus and feed it a bench from another process.

Shared by the live test tier (``tests/live``), the live benchmarks
(``benchmarks/bench_live.py``, ``benchmarks/bench_startup.py``) and the
assembly tests (:func:`live_plant`, :func:`first_valid_in_process`).  The
bus is python-can's ``udp_multicast`` interface: kernel UDP sockets with a
finite receive buffer between processes, which loses frames the way
SocketCAN does when a reader falls behind (and reports them the same way,
see :meth:`online_id.io.bus.CanBus.dropped`).  Each run takes a UDP port of its
own (:func:`free_udp_port`): a socket bound to a port receives what is sent
to every group joined on it, so two runs on one port (two checkouts' suites
at once) would each read the other's bench.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing as mp
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.config import InertiaSettings, ModelSettings, Settings
from online_id.io.bus import CanBus
from online_id.io.dbc import load_dbc
from online_id.io.dbc_output import OutputEncoder
from online_id.service.offload import InlineWorker
from online_id.service.runtime import Runtime

STOPPED = re.compile(r"stopped: (?P<frames_in>\d+) frames in, (?P<frames_out>\d+) frames out, (?P<samples>\d+) samples, "
                     r"(?P<bad>\d+) bad frames, (?P<missing>\d+) missing frames, (?P<dropped>\d+) dropped by the kernel, "
                     r"(?P<foreign>\d+) foreign frames")


def live_plant(seed: int) -> BenchScenario:
    """A bench drawn from a realistic range (resonance 15-35 Hz, damping ratio 0.04-0.12), two steady operating
    points of 35 s."""
    rng = np.random.default_rng(seed)
    J1, J2 = rng.uniform(0.5, 1.2), rng.uniform(0.2, 0.45)
    w0 = 2 * math.pi * rng.uniform(15.0, 35.0)
    zeta = rng.uniform(0.04, 0.12)
    jr = J1 * J2 / (J1 + J2)
    points = (OperatingPoint(float(rng.uniform(1300, 1700)), 35.0),
              OperatingPoint(float(rng.uniform(1900, 2300)), 35.0))
    return dataclasses.replace(BenchScenario(), J1=J1, J2=J2, c_s=w0 ** 2 * jr, d_s=2 * zeta * w0 * jr,
                               operating_points=points, seed=seed)


def live_config(truth: dict, state_dir: Path, input_hz: float | None = None) -> str:
    """The service's configuration for a simulated bench of ``truth`` (its ``bus`` is added by :func:`run_live`):
    the engine inertia and pulses per revolution, the state saved into ``state_dir`` every 5 s, and the input's
    sample rate where ``input_hz`` is given (the default 1 kHz otherwise)."""
    rate = "" if input_hz is None else f"input: {{sample_rate_hz: {input_hz!r}}}\n"
    return (f"inertias: {{J1: {truth['J1']!r}}}\n" + rate
            + f"model: {{pulses_per_rev: {truth['pulses_per_rev']!r}}}\n"
            f"state: {{directory: '{state_dir}', save_interval_s: 5}}\n")


def live_settings(truth: dict) -> Settings:
    """The in-process settings that :func:`live_config` gives the service (for a run of the same frames)."""
    return Settings(inertias=InertiaSettings(J1=truth["J1"]),
                    model=dataclasses.replace(ModelSettings(), pulses_per_rev=truth["pulses_per_rev"]))


def first_valid_in_process(frames: list, settings: Settings) -> float:
    """Stream seconds from the first of ``frames`` to the first valid OidEstimate (nan: none), in-process: the
    service's runtime (:class:`online_id.service.runtime.Runtime`) with ``settings`` and the inline worker, so the
    figure is what the method needs, whatever the machine (the refits run inline, they take no stream time)."""
    db = load_dbc(None)
    estimate_id = int(db.get_message_by_name("OidEstimate").frame_id)
    decode = OutputEncoder(db).decode
    runtime = Runtime(settings, worker=InlineWorker())
    for t, ident, data in frames:
        for fid, out in runtime.on_frame(t, ident, data):
            if fid == estimate_id and decode(fid, out).get("Valid"):
                return float(t - frames[0][0])
    return float("nan")


def free_udp_port() -> int:
    """A UDP port no socket of this machine is bound to now (the kernel's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("", 0))
        return int(sock.getsockname()[1])


def _send(group: str, port: int, frames: list, speed: float, marks: list[int], out,
          min_sleep_s: float = 0.001) -> None:
    """The bench: a separate process sending at ``speed`` x real time; reports the send times of ``marks``."""
    from online_id.io.player import send_paced

    # The bench's sensors send on their own hardware clocks, whatever the PC does; this process stands in for
    # them, so it runs ahead of the machine's other work (when allowed): the service under test sees frames
    # stamped (by the kernel, on arrival) when a bench would send them, not when a busy scheduler let a
    # Python process send them. Run at normal priority on a loaded machine, the sender falls behind and
    # catches up in bursts: frames of 5-20 ms stamped alike, a sample grid distorted, estimates that
    # fail their validity checks.
    try:
        os.nice(-15)
    except OSError:
        pass
    wanted = set(marks)
    stamps: dict[int, float] = {}

    last = [0.0, 0.0]  # perf_counter of the previous send, the longest gap between two sends

    def on_sent(i: int, t: float) -> None:
        if i in wanted:
            stamps[i] = t
        if last[0] and t - last[0] > last[1]:
            last[1] = t - last[0]
        last[0] = t

    # a send that blocks (the loopback's queue full on a loaded machine) delays the bench, it is not a failure
    # of the service under test: the gap is reported (``sender_max_gap_s``) instead of aborting the run
    bus = CanBus("udp_multicast", group, send_timeout_s=5.0, port=port)
    try:
        out.put(("start", time.time(), time.perf_counter()))
        sent = send_paced(bus, frames, speed=speed, on_sent=on_sent, min_sleep_s=min_sleep_s)
        out.put(("done", sent, stamps, last[1]))
    finally:
        bus.close()


@dataclass
class LiveRun:
    """What one run of the service as a process showed."""

    returncode: int
    log: list[str]
    counts: dict[str, int]
    t_bench0: float  # time.time() when the sender started
    # (time.time, perf_counter, signals, kernel arrival stamp (CLOCK_REALTIME)) per OidEstimate received
    estimates: list[tuple[float, float, dict, float]] = field(default_factory=list)
    send_stamps: dict[int, float] = field(default_factory=dict)  # frame index -> sender's perf_counter
    sent: int = 0
    cpu_s: float = float("nan")  # CPU time of the service's receive process (its worker excluded)
    sender_max_gap_s: float = float("nan")  # the longest pause between two of the sender's frames

    @property
    def text(self) -> str:
        return "\n".join(self.log)


def run_live(frames: list, config_text: str, workdir: Path, group: str, speed: float = 1.0,
             marks: list[int] = (), cpu: int | None = None, start_timeout_s: float = 120.0,
             rt_priority: int | None = None, min_sleep_s: float = 0.001) -> LiveRun:
    """Start the service with ``config_text`` (its bus set to ``group``), send ``frames``, stop it, collect.

    ``cpu``: pin the service (and its worker) to this core.  The service is
    stopped with SIGTERM after the sender ends; it first takes what its
    socket still holds.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    config = workdir / "config.yaml"
    port = free_udp_port()
    config.write_text(f"bus: {{interface: udp_multicast, channel: '{group}', options: {{port: {port}}}}}\n"
                      + config_text)
    argv = [sys.executable, "-m", "online_id", "run", "--config", str(config), "--max-seconds", "3600"]
    if rt_priority is not None:  # the receive loop at a real-time priority (SCHED_FIFO), as the unit can run it
        argv = ["chrt", "-f", str(rt_priority), *argv]
    if cpu is not None:
        argv = ["taskset", "-c", str(cpu), *argv]
    service = subprocess.Popen(argv, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                               env=dict(os.environ, PYTHONUNBUFFERED="1"))
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(ln.rstrip() for ln in service.stderr), daemon=True).start()
    db = load_dbc(None)
    encoder = OutputEncoder(db)
    estimate_id = int(db.get_message_by_name("OidEstimate").frame_id)
    estimates: list[tuple[float, float, dict, float]] = []
    stop = threading.Event()

    def consume() -> None:
        bus = CanBus("udp_multicast", group, port=port)
        try:
            while not stop.is_set():
                frame = bus.recv(0.1)
                if frame is not None and frame.arbitration_id == estimate_id:
                    estimates.append((time.time(), time.perf_counter(),
                                      encoder.decode(frame.arbitration_id, frame.data), frame.t_s))
        finally:
            bus.close()

    consumer = threading.Thread(target=consume, daemon=True)
    t_bench0, sent, stamps, cpu_s, max_gap = float("nan"), 0, {}, float("nan"), float("nan")
    try:
        deadline = time.monotonic() + start_timeout_s
        while not any("listening on" in ln for ln in lines):
            if service.poll() is not None or time.monotonic() > deadline:
                raise AssertionError("the service did not start:\n" + "\n".join(lines))
            time.sleep(0.1)
        consumer.start()
        time.sleep(0.5)
        ctx = mp.get_context("spawn")
        out = ctx.Queue()
        sender = ctx.Process(target=_send, args=(group, port, frames, speed, list(marks), out, min_sleep_s),
                             daemon=True)
        sender.start()
        _, t_bench0, _ = out.get(timeout=start_timeout_s)
        duration = (frames[-1][0] - frames[0][0]) / speed
        _, sent, stamps, max_gap = out.get(timeout=duration + start_timeout_s)
        sender.join(timeout=30)
        time.sleep(0.5)
        cpu_s = _cpu_seconds(service.pid)
        service.send_signal(signal.SIGTERM)  # the service takes what its socket still holds, then stops
        rc = service.wait(timeout=120)
    finally:
        stop.set()
        if service.poll() is None:
            service.kill()
            service.wait()
    consumer.join(timeout=5)
    time.sleep(0.2)
    match = next((m for m in map(STOPPED.search, lines) if m), None)
    counts = {k: int(v) for k, v in match.groupdict().items()} if match else {}
    return LiveRun(rc, lines, counts, t_bench0, estimates, stamps, sent, cpu_s, max_gap)


def _cpu_seconds(pid: int) -> float:
    """CPU time (user + system) the process itself used so far (not its worker), from /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")
