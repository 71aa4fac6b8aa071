"""The whole pipeline (decode, assemble, estimate, publish): throughput, latency, memory.

Usage::

    python benchmarks/bench_pipeline.py [--seconds S] [--repeats R] [--latency-s L] [--warm-s W] [--profile]
    python benchmarks/bench_pipeline.py --hour            # memory only: one hour of 1 kHz data
    python benchmarks/bench_pipeline.py --minutes N       # memory only: N minutes

Input: a simulated bench (:func:`simulate_bench`, 1 kHz) encoded into DBC
frames with :func:`encode_inputs` (3 frames per sample: DynoSpeed,
EngineSpeed, DynoTorque); the service configured as ``online-id demo``
configures it (``J1`` and ``pulses_per_rev`` from the simulator, ``J2`` not
given, so the physical parameters are fitted); publications at the default
10 Hz (OidEstimate, OidShaft, OidQuality, OidStatus).

Throughput (``--seconds`` of data at 1500 then 2200 rpm, ``--repeats``
repeats, the two paths interleaved):

* ``Runtime.on_frame`` -- in-process, a plain loop over the frames, no bus;
* ``Service.run`` on the virtual bus -- the real service loop
  (``bus.recv`` -> ``Runtime.on_frame`` -> ``bus.send`` of the outputs, plus
  its state report and watchdog bookkeeping).  All frames are first put on a
  python-can ``virtual`` channel by a sender bus (``preserve_timestamps``);
  the service's queue is unbounded, so they wait.  The time runs from the
  call of ``Service.run`` to its receipt of the last frame; a watcher thread
  stops the service when ``runtime.frames_in`` reaches the frame count.

Both report the median (min .. max) input frames per second, the ratio to the
target of 37,000 frames/s and the multiple of a fully loaded 1 Mbit/s bus
(7,407 frames/s: 8-byte standard frames of 135 bits with worst-case bit
stuffing and the 3-bit intermission; 37,000 frames/s is 5 such buses).

Latency, on a second input (constant 2000 rpm, ``--warm-s`` plus at least
60 s; the estimate becomes valid, state TRACKING, after about 41 s).  Two
measurements, not to be confused:

* in-process: ``Runtime.on_frame`` timed per frame with
  ``time.perf_counter_ns``.  ``on_frame`` returns the frames to publish in the
  same call, so the time of the frame that completes a sample *is* the time
  from that frame to the publication frames (``bus.send`` excluded).  Rows:
  all frames, frames that completed a sample, frames whose outputs carry an
  ``OidEstimate`` (all; while TRACKING; without and with a refit of the
  physical parameters, which happens every ``publish.physical_interval_s``
  while the estimate is valid, deferred to a frame that publishes nothing);
* virtual bus, end to end: ``Service.run`` in a thread; a sender thread puts
  the first ``--warm-s`` seconds of frames on the bus at once (fast-forward to
  a tracking estimator), waits until the service has processed them, then
  sends ``--latency-s`` seconds paced in real time (1 kHz samples, 3 frames
  per ms); a consumer bus in the main thread stamps each ``OidEstimate`` when
  ``recv`` returns it.  Latency = that stamp minus the sender's
  ``perf_counter()`` just before ``send`` of the frame that triggered the
  estimate; which frame that is comes from the in-process run of the same
  frames, and the estimate frames received must be byte-identical to it
  (checked and reported).  A breakdown (sent -> service recv -> service send
  -> consumer recv) comes from stamps in a wrapper around the service's bus.
  Sender, service and consumer share one process and its GIL, which a bench
  (separate devices) does not.

Memory (``--hour`` or ``--minutes N``, run on its own so that the throughput
runs do not inflate the resident set): one-minute chunks of bench data, each
simulated afresh (its own seed, a ramp between two of 1000-2500 rpm that
continues where the previous chunk ended), time-shifted and with the alive
counters continued, go through one ``Runtime.on_frame`` -- one continuous
stream.  The chunks are made one ahead in a helper process (spawned), so
that the simulator's allocations stay out of the measured process, and
arrive packed (20 bytes a frame), so that no minute's worth of Python
objects passes through its allocator: it unpacks one frame at a time, as a
bus delivers them.  VmRSS (``/proc/self/status``) and
``sys.getallocatedblocks()`` (live Python objects: a leak indicator that
allocator fragmentation does not blur) and glibc ``mallinfo2`` (C heap in
use, e.g. NumPy buffers, and free memory the allocator holds) are read
after every simulated minute; the slopes are least-squares fits over minutes 5 to the end.
"""

from __future__ import annotations

import argparse
import cProfile
import ctypes
import gc
import io
import itertools
import multiprocessing
import os
import platform
import pstats
import statistics
import struct
import sys
import threading
import time
from dataclasses import replace

import can
import cantools
import numba
import numpy as np

from online_id.bench import BenchScenario, OperatingPoint, simulate_bench
from online_id.config import BusSettings, InertiaSettings, ModelSettings, Settings
from online_id.io.bus import CanBus
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.service.runtime import Runtime, role_mapping
from online_id.service.live import Service

TARGET_FPS = 37_000.0
# 1 Mbit/s, standard ID, 8 data bytes: 98 stuffable bits (SOF to CRC) + 24 worst-case stuff bits + 10 (CRC
# delimiter, ACK, EOF) + 3 (intermission) = 135 bits per frame.
FULL_BUS_FPS = 1e6 / 135.0
RAMP_S = 3.0
CHUNK_S = 60.0
SPEEDS_RPM = (1000.0, 1500.0, 2000.0, 2500.0, 2000.0, 1500.0)
_channel_ids = itertools.count()


# --- machine and helpers ------------------------------------------------------------------------


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> str:
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return (
        f"{cpu_model()}, {os.cpu_count()} cores ({usable} usable), Python {platform.python_version()}, "
        f"numpy {np.__version__}, numba {numba.__version__}, python-can {can.__version__}, "
        f"cantools {cantools.__version__}, {platform.system()} {platform.release()}, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}"
    )


def proc_status_mb(key: str) -> float:
    """A ``/proc/self/status`` memory field (``VmRSS``, ``VmHWM``) in MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def _mallinfo2():
    try:
        fn = ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return None
    fn.restype = _MallInfo2
    return fn


_MALLINFO2 = _mallinfo2()


def malloc_mb() -> tuple[float, float]:
    """glibc malloc (all arenas): bytes in use (incl. mmapped blocks) and free bytes held, in MiB."""
    if _MALLINFO2 is None:
        return float("nan"), float("nan")
    m = _MALLINFO2()
    return (m.uordblks + m.hblkhd) / 2**20, m.fordblks / 2**20


def pct(values_ns: np.ndarray) -> tuple[float, float, float, float]:
    """p50, p99, p99.9 and max in microseconds."""
    if values_ns.size == 0:
        return (float("nan"),) * 4
    p = np.percentile(values_ns, [50, 99, 99.9]) / 1e3
    return float(p[0]), float(p[1]), float(p[2]), float(values_ns.max()) / 1e3


def fmt_fps(values: list[float]) -> str:
    return f"{statistics.median(values):,.0f} ({min(values):,.0f} .. {max(values):,.0f})"


# --- input data ---------------------------------------------------------------------------------


def bench_record(seconds: float, speeds: tuple[float, ...], seed: int):
    dwell = (seconds - RAMP_S * (len(speeds) - 1)) / len(speeds)
    if dwell <= 0:
        raise SystemExit(f"--seconds must exceed {RAMP_S * (len(speeds) - 1):g} s")
    points = tuple(OperatingPoint(s, dwell) for s in speeds)
    return simulate_bench(BenchScenario(operating_points=points, ramp_s=RAMP_S, seed=seed))


def settings_for(truth: dict, channel: str = "unused") -> Settings:
    """The service as ``online-id demo`` configures it (J1 and pulses per revolution from the bench)."""
    return Settings(
        bus=BusSettings(interface="virtual", channel=channel),
        inertias=InertiaSettings(J1=truth["J1"]),
        model=replace(ModelSettings(), pulses_per_rev=truth["pulses_per_rev"]),
    )


def frames_of(record, db) -> list[tuple[float, int, bytes]]:
    return encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm, record.dyno_torque_nm,
                         db=db)


def estimate_id(db) -> int:
    return int(db.get_message_by_name("OidEstimate").frame_id)


# --- throughput ---------------------------------------------------------------------------------


def run_inprocess(settings: Settings, frames: list) -> tuple[float, Runtime]:
    rt = Runtime(settings)
    on_frame = rt.on_frame
    t0 = time.perf_counter()
    for t_s, ident, data in frames:
        on_frame(t_s, ident, data)
    return time.perf_counter() - t0, rt


def load_bus(frames: list) -> tuple[CanBus, CanBus, str]:
    """A service bus with all frames waiting in its queue, and the sender bus."""
    channel = f"bench-pipeline-{os.getpid()}-{next(_channel_ids)}"
    svc_bus = CanBus("virtual", channel, preserve_timestamps=True)
    sender = CanBus("virtual", channel, preserve_timestamps=True)
    for t_s, ident, data in frames:
        sender.send(ident, data, t_s=t_s)
    queued = svc_bus._bus.queue.qsize()
    if queued != len(frames):
        raise RuntimeError(f"expected {len(frames)} frames queued on the virtual bus, got {queued}")
    return svc_bus, sender, channel


def run_service_drain(settings: Settings, frames: list, profiler: cProfile.Profile | None = None
                      ) -> tuple[float, Service]:
    """Seconds for ``Service.run`` to receive and process all frames already queued on the bus."""
    svc_bus, sender, channel = load_bus(frames)
    service = Service(replace(settings, bus=BusSettings(interface="virtual", channel=channel)),
                      log=io.StringIO(), bus_factory=lambda: svc_bus)
    n = len(frames)

    def stop_when_drained() -> None:
        while service.runtime.frames_in < n and not service.stop_requested:
            time.sleep(0.01)
        service.request_stop()

    watcher = threading.Thread(target=stop_when_drained, daemon=True)
    gc.collect()
    watcher.start()
    if profiler is not None:
        profiler.enable()
    t0 = time.monotonic()
    status = service.run()
    if profiler is not None:
        profiler.disable()
    watcher.join()
    sender.close()
    if status != 0 or service.runtime.frames_in != n:
        raise RuntimeError(f"service ended with status {status} after {service.runtime.frames_in} of {n} frames")
    # last_frame_wall: time.monotonic() when the service received the last frame
    return service.last_frame_wall - t0, service


# --- latency ------------------------------------------------------------------------------------


def latency_inprocess(settings: Settings, frames: list, db) -> dict:
    """Per-frame ``Runtime.on_frame`` times, classified; also the reference for :func:`latency_bus`."""
    est_id = estimate_id(db)
    rt = Runtime(settings)
    on_frame = rt.on_frame
    pipeline = rt.pipeline
    counters = pipeline.assembler.counters
    clock = time.perf_counter_ns
    cpu_clock = time.thread_time_ns  # CPU time: what the publication costs, whatever else the machine does
    n = len(frames)
    dt = np.empty(n, dtype=np.int64)
    cpu = np.empty(n, dtype=np.int64)
    completes = np.zeros(n, dtype=bool)
    reference: list[tuple[int, bytes, str, bool]] = []  # frame index, OidEstimate bytes, state, refit
    for i, (t_s, ident, data) in enumerate(frames):
        before = counters.samples
        next_physical = pipeline._next_physical  # moves when the physical parameters are refitted
        c0 = cpu_clock()
        t0 = clock()
        out = on_frame(t_s, ident, data)
        t1 = clock()
        cpu[i] = cpu_clock() - c0
        dt[i] = t1 - t0
        completes[i] = counters.samples != before
        if out:
            refit = pipeline._next_physical != next_physical and pipeline.last_estimate.valid
            for oid, odata in out:
                if oid == est_id:
                    reference.append((i, odata, pipeline.state.name, refit))
    timer = []
    for _ in range(10000):
        t0 = clock()
        timer.append(clock() - t0)
    idx = np.array([r[0] for r in reference], dtype=int)
    tracking = np.array([r[2] == "TRACKING" for r in reference], dtype=bool)
    refit = np.array([r[3] for r in reference], dtype=bool)
    return {"all": dt, "sample": dt[completes], "publish": dt[idx], "publish_tracking": dt[idx[tracking]],
            "publish_plain": dt[idx[tracking & ~refit]], "publish_refit": dt[idx[refit]],
            "publish_tracking_cpu": cpu[idx[tracking]],
            "timer_ns": float(np.median(timer)), "reference": reference,
            "t_tracking": next((frames[r[0]][0] for r in reference if r[2] == "TRACKING"), None)}


def latency_bus(settings: Settings, frames: list, n_warm: int, reference: list, est_id: int) -> dict:
    """End to end on the virtual bus (see module notes).

    ``frames[:n_warm]`` are sent at once (fast-forward to a tracking estimator); when the service has
    processed them, ``frames[n_warm:]`` are sent paced in real time.  Only estimates triggered by the paced
    frames count.  The service's bus is instrumented (receive and send stamps) for the breakdown.
    """
    channel = f"bench-pipeline-{os.getpid()}-{next(_channel_ids)}"
    svc_bus = CanBus("virtual", channel, preserve_timestamps=True)
    consumer = CanBus("virtual", channel)
    sender = CanBus("virtual", channel, preserve_timestamps=True)
    service = Service(replace(settings, bus=BusSettings(interface="virtual", channel=channel)),
                      log=io.StringIO(), bus_factory=lambda: svc_bus)
    n = len(frames)
    clock = time.perf_counter
    send_t = [0.0] * n
    svc_rx_t: list[float] = []  # service's recv of frame k (FIFO: the k-th frame it receives is frames[k])
    svc_est_t: list[float] = []  # service's bus.send of the k-th OidEstimate
    orig_recv, orig_send = svc_bus.recv, svc_bus.send

    def recv(timeout: float):
        frame = orig_recv(timeout)
        if frame is not None:
            svc_rx_t.append(clock())
        return frame

    def send(arbitration_id: int, data: bytes, *a, **k) -> None:
        if arbitration_id == est_id:
            svc_est_t.append(clock())
        orig_send(arbitration_id, data, *a, **k)

    svc_bus.recv, svc_bus.send = recv, send
    done = threading.Event()

    def send_frames() -> None:
        for t_s, ident, data in frames[:n_warm]:
            sender.send(ident, data, t_s=t_s)
        while service.runtime.frames_in < n_warm:  # the service keeps busy: no silence, no tick
            time.sleep(0.0002)
        t_first = frames[n_warm][0]
        wall0 = clock()
        for i in range(n_warm, n):
            t_s, ident, data = frames[i]
            delay = wall0 + (t_s - t_first) - clock()
            if delay > 0:
                time.sleep(delay)
            send_t[i] = clock()
            sender.send(ident, data, t_s=t_s)
        done.set()

    svc_thread = threading.Thread(target=service.run, name="service", daemon=True)
    send_thread = threading.Thread(target=send_frames, name="sender", daemon=True)
    gc.collect()
    svc_thread.start()
    time.sleep(0.2)
    send_thread.start()
    received: list[tuple[float, bytes]] = []
    idle_since = None
    while True:
        frame = consumer.recv(0.02)
        now = clock()
        if frame is not None:
            idle_since = None
            if frame.arbitration_id == est_id:
                received.append((now, frame.data))
            continue
        if done.is_set() and service.runtime.frames_in >= n:
            idle_since = idle_since or now
            if now - idle_since > 0.1:
                break
    service.request_stop()
    svc_thread.join(timeout=10)
    send_thread.join(timeout=10)
    consumer.close()
    sender.close()
    ref = [r for r in reference if r[0] < n]
    matched = sum(1 for r, (_, d_rx) in zip(ref, received) if r[1] == d_rx)
    rows = [(k, r) for k, r in enumerate(ref) if r[0] >= n_warm and k < len(received) and k < len(svc_est_t)]
    total = np.array([(received[k][0] - send_t[r[0]]) * 1e9 for k, r in rows])
    wake = np.array([(svc_rx_t[r[0]] - send_t[r[0]]) * 1e9 for k, r in rows])
    proc = np.array([(svc_est_t[k] - svc_rx_t[r[0]]) * 1e9 for k, r in rows])
    deliver = np.array([(received[k][0] - svc_est_t[k]) * 1e9 for k, r in rows])
    refit = np.array([r[3] for k, r in rows], dtype=bool)
    states = sorted({r[2] for k, r in rows})
    return {"total": total, "total_plain": total[~refit], "total_refit": total[refit], "wake": wake,
            "proc": proc, "deliver": deliver, "n_ref": len(ref), "n_rx": len(received), "matched": matched,
            "n_paced": n - n_warm, "n_warm": n_warm, "states": states,
            "paced_wall_s": send_t[-1] - send_t[n_warm], "paced_stream_s": frames[-1][0] - frames[n_warm][0]}


# --- memory -------------------------------------------------------------------------------------


def counter_bytes(db, settings: Settings) -> dict[int, int]:
    """Input frame ID -> byte of its alive counter (one little-endian byte each), to continue the counters."""
    m = role_mapping(settings.mapping)
    out = {}
    for rs in m.dyno_speed, m.engine_speed, m.dyno_torque:
        msg = db.get_message_by_name(rs.message)
        sig = msg.get_signal_by_name(rs.counter)
        if sig.start % 8 or sig.length != 8 or sig.byte_order != "little_endian":
            raise SystemExit(f"counter {sig.name} is not one little-endian byte; cannot continue it")
        out[int(msg.frame_id)] = sig.start // 8
    return out


_chunk_db = None


FRAME_RECORD = struct.Struct("<dI8s")  # t_s, arbitration ID, 8 data bytes


def make_chunk(k: int) -> bytes:
    """Minute ``k`` of one continuous stream (see module notes), packed as :data:`FRAME_RECORD` records.

    Runs in the helper process.  Packed, so that the measured process holds no minute's worth of Python
    objects: it unpacks one frame at a time, as a bus delivers them.
    """
    global _chunk_db
    if _chunk_db is None:
        _chunk_db = load_dbc(None)
    db = _chunk_db
    counter_byte = counter_bytes(db, Settings())
    a, b = SPEEDS_RPM[k % len(SPEEDS_RPM)], SPEEDS_RPM[(k + 1) % len(SPEEDS_RPM)]
    rec = bench_record(CHUNK_S, (a, b), seed=1000 + k)
    frames = frames_of(rec, db)
    per_id = rec.time_s.size  # frames per message and chunk (no decimation)
    count = {fid: k * per_id for fid in counter_byte}
    shift = k * CHUNK_S
    out = bytearray()
    for t_s, ident, data in frames:
        if len(data) != 8:
            raise SystemExit(f"expected 8-byte input frames, got {len(data)} bytes for ID 0x{ident:X}")
        byte = counter_byte.get(ident)
        if byte is not None:
            d = bytearray(data)
            d[byte] = count[ident] & 0xFF
            count[ident] += 1
            data = bytes(d)
        out += FRAME_RECORD.pack(t_s + shift, ident, data)
    return bytes(out)


def _chunk_worker(conn) -> None:
    """Helper process: sends chunk ``k`` on request, then makes chunk ``k + 1`` ahead of the next one."""
    ahead: dict[int, bytes] = {}
    while True:
        k = conn.recv()
        if k is None:
            break
        frames = ahead.pop(k, None)
        conn.send_bytes(frames if frames is not None else make_chunk(k))
        ahead = {k + 1: make_chunk(k + 1)}
    conn.close()


def run_memory(minutes: int, db) -> int:
    truth = bench_record(CHUNK_S, SPEEDS_RPM[:2], seed=1000).truth
    settings = settings_for(truth)
    # the chunks are simulated and encoded one ahead in a helper process, so that the simulator's
    # allocations do not show in this process, which holds one chunk at a time
    ctx = multiprocessing.get_context("spawn")
    conn, child_conn = ctx.Pipe()
    helper = ctx.Process(target=_chunk_worker, args=(child_conn,), daemon=True)
    helper.start()

    def chunk(k: int) -> bytes:
        conn.send(k)
        return conn.recv_bytes()

    # warm-up in a throw-away runtime (numba compile or cache load, imports)
    run_inprocess(settings, list(FRAME_RECORD.iter_unpack(chunk(0)))[:6000])
    gc.collect()
    rt = Runtime(settings)
    on_frame = rt.on_frame
    rss = [proc_status_mb("VmRSS")]
    blocks = [sys.getallocatedblocks()]
    heap = [malloc_mb()]
    t_wall0 = time.perf_counter()
    t_proc = 0.0
    for k in range(minutes):
        frames = chunk(k)
        t0 = time.perf_counter()
        for t_s, ident, data in FRAME_RECORD.iter_unpack(frames):
            on_frame(t_s, ident, data)
        t_proc += time.perf_counter() - t0
        del frames
        rss.append(proc_status_mb("VmRSS"))
        blocks.append(sys.getallocatedblocks())
        heap.append(malloc_mb())
        print(f"  minute {k + 1:3d}: VmRSS {rss[-1]:7.1f} MiB, malloc in use {heap[-1][0]:6.1f} MiB, free held "
              f"{heap[-1][1]:6.1f} MiB, {blocks[-1]:,} Python blocks, {rt.frames_in:,} frames, state "
              f"{rt.pipeline.state.name}", file=sys.stderr, flush=True)
    conn.send(None)
    helper.join(timeout=30)
    wall = time.perf_counter() - t_wall0
    mins = np.arange(len(rss), dtype=float)
    keep = mins >= 5
    enough = keep.sum() >= 2
    slope = float(np.polyfit(mins[keep], np.array(rss)[keep], 1)[0]) * 60.0 if enough else float("nan")
    in_use = np.array([h[0] for h in heap])
    h_slope = float(np.polyfit(mins[keep], in_use[keep], 1)[0]) * 60.0 if enough else float("nan")
    b_slope = float(np.polyfit(mins[keep], np.array(blocks, float)[keep], 1)[0]) * 60.0 if enough else float("nan")
    step = 10 if minutes >= 20 else max(1, minutes // 6)
    marks = sorted(set(range(0, minutes + 1, step)) | {minutes})
    p = rt.pipeline
    c = p.counters

    print(f"Machine: {machine()}")
    print(f"Memory: {minutes} min of 1 kHz bench data ({rt.frames_in:,} input frames, {rt.frames_out:,} output "
          f"frames) through one Runtime.on_frame; wall {wall:.0f} s, of which on_frame {t_proc:.0f} s "
          f"({rt.frames_in / t_proc:,.0f} frames/s), chunks simulated and encoded one ahead in a helper process")
    print(f"End state {p.state.name}, {c.samples:,} samples, {c.gaps} gaps, {c.timeouts} timeouts, "
          f"{c.bad_frames} bad frames, {c.missing_frames} missing frames; lists kept by the pipeline: "
          f"{len(p.events)} events, {len(p.alerts)} alerts")
    print()
    print("| stream time [min] | " + " | ".join(str(m) for m in marks) + " |")
    print("|---|" + "---:|" * len(marks))
    print("| VmRSS [MiB] | " + " | ".join(f"{rss[m]:.1f}" for m in marks) + " |")
    print("| malloc in use [MiB] | " + " | ".join(f"{heap[m][0]:.1f}" for m in marks) + " |")
    print("| malloc free, held [MiB] | " + " | ".join(f"{heap[m][1]:.1f}" for m in marks) + " |")
    print("| Python blocks allocated | " + " | ".join(f"{blocks[m]:,}" for m in marks) + " |")
    print()
    tail = rss[5:] if minutes >= 6 else rss
    slope_text = (f"{slope:+.2f} MiB/hour (malloc in use {h_slope:+.2f} MiB/hour, Python blocks "
                  f"{b_slope:+,.0f}/hour)" if minutes >= 6
                  else "n/a (needs at least 6 minutes)")
    print(f"Slope of VmRSS over minutes {min(5, minutes)}..{minutes}: {slope_text} (least squares over the "
          f"per-minute samples); VmRSS over that span min {min(tail):.1f}, max {max(tail):.1f} MiB; "
          f"VmHWM {proc_status_mb('VmHWM'):.1f} MiB")
    return 0


# --- main ---------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0,
                        help="seconds of 1 kHz bench data for the throughput runs (default 60 = 180k frames)")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of each throughput run (default 5)")
    parser.add_argument("--latency-s", type=float, default=20.0,
                        help="seconds of real-time paced sending for the virtual-bus latency (default 20; 0 skips)")
    parser.add_argument("--warm-s", type=float, default=45.0,
                        help="seconds of stream sent at once before the paced part, to reach TRACKING (default 45)")
    parser.add_argument("--profile", action="store_true",
                        help="also profile one Service.run drain (cProfile, top 20 by own time)")
    parser.add_argument("--hour", action="store_true", help="memory only: replay one hour (= --minutes 60)")
    parser.add_argument("--minutes", type=int, default=None, help="memory only: replay N minutes")
    args = parser.parse_args(argv)
    db = load_dbc(None)

    if args.hour or args.minutes is not None:
        return run_memory(60 if args.hour else args.minutes, db)

    t0 = time.perf_counter()
    record = bench_record(args.seconds, (1500.0, 2200.0), seed=1)
    frames = frames_of(record, db)
    settings = settings_for(record.truth)
    est_id = estimate_id(db)
    print(f"Generated {len(frames):,} frames ({args.seconds:g} s at 1 kHz) in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)

    # warm-up: numba compile (or cache load), first calls
    run_inprocess(settings, frames[:6000])
    run_service_drain(settings, frames[:6000])

    fps: dict[str, list[float]] = {"inproc": [], "service": []}
    outputs: dict[str, set[int]] = {"inproc": set(), "service": set()}
    for r in range(args.repeats):
        gc.collect()
        dt, rt = run_inprocess(settings, frames)
        fps["inproc"].append(len(frames) / dt)
        outputs["inproc"].add(rt.frames_out)
        dt, service = run_service_drain(settings, frames)
        fps["service"].append(len(frames) / dt)
        outputs["service"].add(service.runtime.frames_out)
        final_state = service.runtime.pipeline.state.name
        print(f"  repeat {r + 1}: on_frame {fps['inproc'][-1]:,.0f} frames/s, Service.run "
              f"{fps['service'][-1]:,.0f} frames/s", file=sys.stderr, flush=True)

    # latency stream: constant 2000 rpm; the estimator tracks after about 41 s
    t0 = time.perf_counter()
    lat_s = args.warm_s + max(args.latency_s, 60.0)
    lat_record = bench_record(lat_s, (2000.0,), seed=2)
    lat_frames = frames_of(lat_record, db)
    lat_settings = settings_for(lat_record.truth)
    print(f"Generated {len(lat_frames):,} latency frames ({lat_s:g} s) in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr)
    gc.collect()
    lat = latency_inprocess(lat_settings, lat_frames, db)
    bus_lat = None
    if args.latency_s > 0:
        n_warm = int(round(args.warm_s * 1000)) * 3
        n_bus = n_warm + int(round(args.latency_s * 1000)) * 3
        print(f"Virtual-bus latency: {n_warm:,} frames at once, then {n_bus - n_warm:,} paced in real time ...",
              file=sys.stderr, flush=True)
        bus_lat = latency_bus(lat_settings, lat_frames[:n_bus], n_warm, lat["reference"], est_id)

    print(f"Machine: {machine()}")
    print()
    print(f"Throughput input: {len(frames):,} frames = {args.seconds:g} s of simulated 1 kHz bench data (3 frames "
          f"per sample), 1500 then 2200 rpm, final state {final_state}; publication at "
          f"{settings.publish.rate_hz:g} Hz (OidEstimate, OidQuality, OidStatus; OidShaft every "
          f"{settings.publish.physical_interval_s:g} s while valid); output frames per run: in-process "
          f"{sorted(outputs['inproc'])}, service {sorted(outputs['service'])}. {args.repeats} repeats, "
          f"interleaved; median (min .. max) input frames/s. Target {TARGET_FPS:,.0f} frames/s = 5 x a fully "
          f"loaded 1 Mbit/s bus ({FULL_BUS_FPS:,.0f} frames/s of 135-bit frames).")
    print()
    print("| path | input frames/s | / 37,000 target | x full 1 Mbit/s bus | us/frame |")
    print("|---|---:|---:|---:|---:|")
    for key, name in (("inproc", "Runtime.on_frame, in-process (no bus)"),
                      ("service", "Service.run on the virtual bus (recv -> on_frame -> send)")):
        med = statistics.median(fps[key])
        print(f"| {name} | {fmt_fps(fps[key])} | {med / TARGET_FPS:.2f} | {med / FULL_BUS_FPS:.1f} | "
              f"{1e6 / med:.1f} |")
    print()
    t_tr = lat["t_tracking"]
    print(f"Latency input: {len(lat_frames):,} frames = {lat_s:g} s at a constant 2000 rpm; the estimate is valid "
          f"(TRACKING) from {'never' if t_tr is None else f'{t_tr:.1f} s'}. A publication with a refit "
          f"carries OidShaft: the physical parameters are refitted (scipy least_squares, J2 not configured) "
          f"every {lat_settings.publish.physical_interval_s:g} s, on the next frame that publishes nothing (deferred, so it never delays an estimate).")
    print(f"* in-process: Runtime.on_frame timed per frame with perf_counter_ns (timer overhead about "
          f"{lat['timer_ns']:.0f} ns included), garbage collector on. The frame that completes a sample returns "
          f"the sample's publication frames in the same call, so its time is the last-frame-to-publication "
          f"latency (bus.send not included).")
    if bus_lat is not None:
        b = bus_lat
        print(f"* virtual bus, end to end: Service.run in one thread; a sender thread puts the first "
              f"{b['n_warm']:,} frames ({args.warm_s:g} s) on the bus at once, waits until the service has "
              f"processed them, then sends {b['n_paced']:,} frames ({b['paced_stream_s']:.1f} s of stream) paced in "
              f"real time (took {b['paced_wall_s']:.1f} s); a consumer bus in the main thread stamps each "
              f"OidEstimate when recv returns it. Latency = that stamp minus the sender's perf_counter() just "
              f"before send of the frame that triggered the estimate (from the in-process reference run). "
              f"Only estimates triggered by paced frames count (states {', '.join(b['states'])}). "
              f"{b['n_rx']} estimates received of {b['n_ref']} expected, {b['matched']} byte-identical to the "
              f"reference. Breakdown from stamps in the service's bus wrapper. Sender, service and consumer "
              f"share one process and one GIL (on a bench they are separate devices).")
    print()
    print("| latency | count | p50 [us] | p99 [us] | p99.9 [us] | max [us] |")
    print("|---|---:|---:|---:|---:|---:|")
    rows = [("in-process, all frames", lat["all"]),
            ("in-process, frames completing a sample", lat["sample"]),
            ("in-process, frames publishing an estimate (any state)", lat["publish"]),
            ("in-process, ... while TRACKING", lat["publish_tracking"]),
            ("in-process, ... while TRACKING, CPU time (thread_time_ns)", lat["publish_tracking_cpu"]),
            ("in-process, ... while TRACKING, without refit", lat["publish_plain"]),
            ("in-process, ... with refit (OidShaft)", lat["publish_refit"])]
    if bus_lat is not None:
        rows += [("virtual bus, last frame sent -> OidEstimate received", bus_lat["total"]),
                 ("virtual bus, ... without refit", bus_lat["total_plain"]),
                 ("virtual bus, ... with refit (OidShaft)", bus_lat["total_refit"]),
                 ("virtual bus, breakdown: sent -> service recv", bus_lat["wake"]),
                 ("virtual bus, breakdown: service recv -> service send OidEstimate", bus_lat["proc"]),
                 ("virtual bus, breakdown: service send -> consumer recv", bus_lat["deliver"])]
    for name, values in rows:
        p50, p99, p999, mx = pct(values)
        print(f"| {name} | {values.size:,} | {p50:.1f} | {p99:.1f} | {p999:.1f} | {mx:.1f} |")

    if args.profile:
        prof = cProfile.Profile()
        run_service_drain(settings, frames, profiler=prof)
        print()
        print("Profile of one Service.run drain of the throughput input (cProfile, top 20 by own time):")
        out = io.StringIO()
        pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(20)
        print(out.getvalue())
        # the publishing frames of the latency input (the ones that carry the estimate)
        prof = cProfile.Profile()
        rt = Runtime(lat_settings)
        publishing = {r[0] for r in lat["reference"]}
        for i, (t_s, ident, data) in enumerate(lat_frames):
            if i in publishing:
                prof.enable()
                rt.on_frame(t_s, ident, data)
                prof.disable()
            else:
                rt.on_frame(t_s, ident, data)
        print(f"Profile of the {len(publishing)} on_frame calls that publish an estimate, latency input "
              f"(cProfile, top 25 by cumulative time):")
        out = io.StringIO()
        pstats.Stats(prof, stream=out).sort_stats("cumulative").print_stats(25)
        print(out.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
