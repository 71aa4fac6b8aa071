"""The daemon: one receive loop, signals, systemd notify/watchdog, persisted state.

``run_service(settings)`` opens the bus, restores the saved state, and loops:
receive a frame (with a short timeout), run it through the :class:`Runtime`,
send what it publishes, and between frames advance the stream clock so that
silence is detected (from the time of the last frame the pipeline took,
never from a frame judged bad).  SIGTERM and SIGINT end the loop cleanly: the
excitation request is withdrawn, the state is saved, the bus closed, exit
status 0; 1 when that last save failed (the state on disk is then older than
the service's), so that systemd sees it.

Nothing slow runs in the receive loop: the window refits, multi-start
checks and physical fits go to a worker process at the lowest CPU priority
(:class:`~online_id.service.offload.ProcessWorker`) and are adopted between frames,
so a refit never stops the loop from reading the socket. The kernel's count
of frames dropped on a full receive buffer is read once a second, counted
(``MissingFrames`` in the status frame, ``dropped_frames`` in the counters)
and logged.

A bus that fails is reopened with exponential back-off (0.1 s doubling to
5 s); if it stays down for longer than ``bus.reopen_max_s`` the process ends
with status 1, so that systemd restarts it (``Restart=on-failure``). A bus
that cannot open for a reason retrying cannot heal (no CAN in the kernel, an
unknown interface, a missing package) ends the process at once with status
2 and a one-line error saying what to fix (``RestartPreventExitStatus=2``).

The watchdog (``WatchdogSec=`` in the unit) is pinged only while the loop
runs and input frames flow; status text goes to systemd (``STATUS=``) and
a log line to stderr (the journal) on every state change.
"""

from __future__ import annotations

import gc
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, TextIO

from online_id.service.commands import FRESHNESS_FILE, keep_freshness
from online_id.config import Settings
from online_id.errors import BusError
from online_id.io.bus import CanBus
from online_id.io.statefile import save_state
from online_id.io.journal import Journal
from online_id.io.systemd import Notifier
from online_id.service.offload import ProcessWorker
from online_id.service.reaction import ReactionTimes
from online_id.records import AlertKind, AlertOut, FrameFault
from online_id.service.restore import restore_pipeline
from online_id.service.runtime import Runtime
from online_id.service.scheduling import Collector, request_short_slice

STATE_FILE = "online-id-state.json"
RECV_TIMEOUT_S = 0.05  # the loop wakes at least this often on a silent bus (timeouts, worker results)
CHORES_S = 0.02  # state report, drop count, watchdog and save: checked at most this often
DRAIN_MAX_S = 5.0  # on stop, frames already in the kernel's receive buffer are processed for at most this long


def state_path(settings: Settings) -> Path | None:
    """Where the state is saved: ``state.directory``, else ``$STATE_DIRECTORY`` (systemd), else nowhere."""
    directory = settings.state.directory or (os.environ.get("STATE_DIRECTORY", "").split(":")[0] or None)
    return Path(directory) / STATE_FILE if directory else None


class Service:
    """The live service around a :class:`Runtime` (see module notes)."""

    def __init__(self, settings: Settings, log: TextIO | None = None,
                 bus_factory: Callable[[], CanBus] | None = None, clock: Callable[[], float] = time.monotonic,
                 worker=None) -> None:
        self.settings = settings
        self.log = log or sys.stderr
        # the slow work in a low-priority child process (tests may pass an InlineWorker for determinism)
        self.runtime = Runtime(settings, worker=worker if worker is not None else ProcessWorker())
        self.notifier = Notifier()
        self.journal = Journal()
        self._hooks: list = []
        self.clock = clock
        b = settings.bus
        self.bus_factory = bus_factory or (lambda: CanBus(b.interface, b.channel, b.bitrate, b.receive_own_messages,
                                                             options=b.options))
        self.stop_requested = False
        self.state_file = state_path(settings)
        self.last_frame_wall = 0.0
        self.last_frame_ts: float | None = None
        self.reaction = ReactionTimes()  # input frame arrival -> its first output sent (see online_id.service.reaction)
        self.processing = ReactionTimes()  # the same output: from the loop receiving the frame to it sent
        self.processing_cpu = ReactionTimes()  # ... and the CPU time of this thread meanwhile (time.thread_time)
        # ... by phase (CPU time): decoding and the pipeline, encoding the OidEstimate, sending it; and before it,
        # the wait from the frame's arrival to the loop taking it off the socket (wall time)
        self.phases = {what: ReactionTimes() for what in ("pipeline CPU", "encoding CPU", "sending CPU", "waiting")}
        self._last_state = None
        self._restore()
        if self.state_file is not None:  # a command's freshness value outlives a restart (online_id.service.commands)
            keep_freshness(self.runtime.commands, self.state_file.with_name(FRESHNESS_FILE), self.say)
        self._n_alerts = self.runtime.pipeline.alerts_total
        self.runtime.pipeline.warm_up()  # compiled code loaded before the bus opens, not on the first frames
        self.telemetry = None
        if settings.mqtt.host:  # MQTT telemetry: publications queued here, sent by its own threads
            from online_id.io.mqtt import MqttTelemetry
            self.telemetry = MqttTelemetry(settings.mqtt, self.say)
            self.runtime.on_publish = self.telemetry.publish

    # -- state ---------------------------------------------------------------------------------------
    def say(self, text: str) -> None:
        print(f"online-id: {text}", file=self.log, flush=True)

    def _restore(self) -> None:
        if self.state_file is None:
            return
        # all or nothing; the restored pipeline's slow work goes where ours did
        pipeline = restore_pipeline(self.state_file, self.settings, self.say, worker=self.runtime.pipeline.worker)
        if pipeline is not None:
            self.runtime.pipeline = pipeline

    def save(self, final: bool = False) -> bool:
        """Save the state: in the worker process while running (the write and fsync take tens of ms),
        here and now at the end (``final``); False when a save here failed (said)."""
        if self.state_file is None:
            return True
        state = self.runtime.pipeline.get_state()  # a snapshot (about 0.5 ms)
        worker = self.runtime.pipeline.worker
        if final or not worker.asynchronous:
            try:
                save_state(self.state_file, state)
            except OSError as err:
                self.say(f"cannot save state to {self.state_file}: {err}")
                return False
        elif not worker.busy("state"):
            worker.submit("state", save_state, (self.state_file, state), self._saved)
        return True

    def _saved(self, _result, error: str | None) -> None:
        if error is not None:
            self.say(f"cannot save state to {self.state_file}: {error}")

    # -- loop ----------------------------------------------------------------------------------------
    def request_stop(self, *_args) -> None:
        self.stop_requested = True

    def _open(self, deadline: float | None = None) -> CanBus:
        """Open the bus, retrying with back-off while it may come up (see module notes)."""
        delay, down_since = 0.1, self.clock()
        while True:
            try:
                return self.bus_factory()
            except BusError as err:
                if getattr(err, "permanent", False):
                    raise
                if self.clock() - down_since > self.settings.bus.reopen_max_s:
                    raise BusError(f"{err}; gave up after {self.settings.bus.reopen_max_s:g} s "
                                   f"(bus.reopen_max_s)") from err
                if deadline is not None and time.monotonic() + delay > deadline:
                    raise BusError(f"{err}; stopped retrying at the time limit") from err
                self.say(f"{err}; retrying in {delay:.1f} s")
                self.notifier.status(f"bus down: {err}")
                end = time.monotonic() + delay
                while time.monotonic() < end and not self.stop_requested:
                    time.sleep(0.05)
                if self.stop_requested:
                    raise
                delay = min(2 * delay, 5.0)

    def _dispatch_alert(self, a: AlertOut) -> None:
        """An alert to the log, the journal (structured) and the optional command hook."""
        self.say(f"alert {a.kind.name} (severity {a.severity}): {a.message}")
        fields = {
            "FAULT_CODE": a.kind.name,
            "SEVERITY": {1: "warning", 2: "fault"}.get(a.severity, str(a.severity)),
            "SPEED_RPM": f"{a.speed_rpm:.0f}",
            "STREAM_TIME_S": f"{a.t_s:.3f}",
        }
        if a.kind == AlertKind.FREQ_DRIFT:
            fields["FREQ_DRIFT_PCT"] = f"{a.value_pct:.2f}"
        elif a.kind == AlertKind.DAMPING_DRIFT:
            fields["DAMPING_DRIFT_PCT"] = f"{a.value_pct:.2f}"
        if self.settings.alerts.journal:
            self.journal.send(a.message, priority=2 if a.severity >= 2 else 4, **fields)
        cmd = self.settings.alerts.command
        if cmd:
            env = dict(os.environ, ONLINE_ID_ALERT_MESSAGE=a.message,
                       **{f"ONLINE_ID_{k}": v for k, v in fields.items()})
            try:
                self._hooks.append((time.monotonic(), subprocess.Popen(
                    shlex.split(cmd), env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL, start_new_session=True)))
            except OSError as err:
                self.say(f"alert command {cmd!r} failed to start: {err}")

    def _reap_hooks(self) -> None:
        keep = []
        for started, proc in self._hooks:
            if proc.poll() is None:
                if time.monotonic() - started > self.settings.alerts.command_timeout_s:
                    proc.kill()
                    self.say(f"alert command killed after {self.settings.alerts.command_timeout_s:g} s")
                else:
                    keep.append((started, proc))
        self._hooks = keep

    def _report_state(self) -> None:
        for text in self.runtime.commands.take_log():  # every command frame, with what was done
            self.say(text)
        p = self.runtime.pipeline
        new = p.alerts_total - self._n_alerts
        if new > 0:
            for a in p.alerts[-min(new, len(p.alerts)):]:
                self._dispatch_alert(a)
        self._n_alerts = p.alerts_total
        if self._hooks:
            self._reap_hooks()
        if p.state != self._last_state:
            self._last_state = p.state
            est = p.estimate
            f0 = f", f0 {est.f0_hz:.3f} Hz" if est is not None and est.valid else ""
            c = p.counters
            text = f"{p.state.name}{f0}, {c.samples} samples, {c.bad_frames} bad frames"
            self.say(f"state {text}")
            self.notifier.status(text)

    def _commands_text(self) -> str:
        gate = self.runtime.commands
        why = ", ".join(f"{n} {reason}" for reason, n in sorted(gate.refusals.items()))
        return f"{gate.accepted} commands accepted, {gate.refused} rejected" + (f" ({why})" if why else "")

    def _close_telemetry(self) -> None:
        if self.telemetry is not None:
            self.telemetry.close(self.runtime.pipeline.state.name)

    def _check_drops(self, bus: CanBus) -> None:
        """Add the kernel's new drops (full receive buffer) to the counters, and say so."""
        total = bus.dropped()
        if total is None:
            return
        if self._drops_base is None or total < self._drops_base:
            self._drops_base = total  # a new socket: count from here
            return
        new = total - self._drops_base
        self._drops_base = total
        if new > 0:
            self.runtime.pipeline.on_dropped(new)
            self.say(f"the kernel dropped {new} frames (receive buffer full; "
                     f"{self.runtime.pipeline.dropped_frames} since start)")

    def run(self, max_s: float | None = None) -> int:
        """The receive loop; returns the exit status."""
        s = self.settings
        t_start = time.monotonic()
        self._drops_base: int | None = None
        try:
            bus = self._open(None if max_s is None else t_start + max_s)
        except BusError as err:
            self.say(f"bus down: {err}")
            self.runtime.pipeline.worker.close()
            self._close_telemetry()
            return 2 if getattr(err, "permanent", False) else 1
        rcvbuf = getattr(bus, "receive_buffer_bytes", None)
        self.say(f"listening on {s.bus.interface}:{s.bus.channel}"
                 + (f" (kernel receive buffer {rcvbuf} bytes)" if rcvbuf else ""))
        self.say(self.runtime.commands.mode_text())  # authenticated or not
        self.say(request_short_slice())  # this thread preempts the worker and other work when a frame comes
        self.notifier.ready(f"listening on {s.bus.interface}:{s.bus.channel}")
        next_drops = time.monotonic() + 1.0
        next_save = time.monotonic() + s.state.save_interval_s
        next_ping = 0.0
        ping_every = (self.notifier.watchdog_s or 10.0) / 3
        draining_until = None
        next_chores = 0.0
        runtime, monotonic, wall, cpu = self.runtime, time.monotonic, time.time, time.thread_time
        reaction, processing, processing_cpu = self.reaction, self.processing, self.processing_cpu
        pipeline_cpu, encoding_cpu, sending_cpu, waiting = self.phases.values()
        collector = Collector()
        try:
            while True:
                # the hot path: one frame in, its outputs out; everything else at most every CHORES_S
                try:
                    frame = bus.recv(RECV_TIMEOUT_S if draining_until is None else 0.0)
                    t_recv = wall()
                    c_recv = cpu()
                    now = monotonic()
                    if frame is not None:
                        before = runtime.stream_clock
                        pubs = runtime.publications(frame.t_s, frame.arbitration_id, frame.data,
                                                    frame.is_extended, frame.is_error)
                        clock = runtime.stream_clock
                        if clock != before and clock == clock:  # this frame moved it (and it is not NaN)
                            # the loop's clock follows the frames the pipeline took, never a bad one's time
                            self.last_frame_ts, self.last_frame_wall = clock, now
                        if pubs:
                            # a publication's first frame is its OidEstimate: encoded and sent before anything
                            # else is encoded, and before the rest of the publication is made
                            c_made = cpu()
                            first = runtime.first_frame(pubs[0])
                            c_encoded = cpu()
                            if first is not None:  # (None: an output the DBC lacks)
                                bus.send(*first)
                                t_sent = wall()
                                c_sent = cpu()
                                reaction.add(t_sent - frame.t_s)
                                processing.add(t_sent - t_recv)
                                processing_cpu.add(c_sent - c_recv)
                                pipeline_cpu.add(c_made - c_recv)
                                encoding_cpu.add(c_encoded - c_made)
                                sending_cpu.add(c_sent - c_encoded)
                                waiting.add(t_recv - frame.t_s)
                            for ident, data in runtime.frames(pubs, skip_first=True):
                                bus.send(ident, data)
                            more = runtime.finish()
                            if more:
                                for ident, data in runtime.frames(more):
                                    bus.send(ident, data)
                        out = None
                    elif draining_until is not None:
                        break
                    elif self.last_frame_ts is not None:
                        # the stream's clock: the last good frame's time plus the wall time since it came
                        # (frame timestamps may be kernel time, a replayed log's or a simulator's)
                        out = runtime.tick(self.last_frame_ts + now - self.last_frame_wall)
                    else:
                        out = runtime.tick_worker()
                    if out:
                        for ident, data in out:
                            bus.send(ident, data)
                except BusError as err:
                    runtime.finish()  # the rest of a publication whose first frame failed: its frames are lost
                    self.say(f"bus failed: {err}; reopening")
                    bus.close()
                    self._drops_base = None
                    bus = self._open(None if max_s is None else t_start + max_s)
                    continue
                if now < next_chores or (self.last_frame_ts is not None and runtime.pipeline.publication_near(
                        self.last_frame_ts + now - self.last_frame_wall)):
                    continue  # (not while a publication is near: they take up to milliseconds, see QUIET_S)
                next_chores = now + CHORES_S
                collector.collect()
                if draining_until is None and (self.stop_requested or (max_s is not None and now - t_start > max_s)):
                    # stop: first take what the kernel already holds for us (bounded), then end
                    draining_until = now + DRAIN_MAX_S
                elif draining_until is not None and now > draining_until:
                    self.say(f"stopped draining the receive buffer after {DRAIN_MAX_S:g} s")
                    break
                if now >= next_drops:
                    self._check_drops(bus)
                    next_drops = now + 1.0
                self._report_state()
                flowing = now - self.last_frame_wall < s.input.timeout_s
                if flowing and now >= next_ping:
                    self.notifier.watchdog()
                    next_ping = now + ping_every
                if now >= next_save:
                    self.save()
                    next_save = now + s.state.save_interval_s
        except BusError as err:
            self.say(f"bus down: {err}")
            self.save(final=True)
            return 2 if getattr(err, "permanent", False) else 1
        finally:
            collector.close()
            self._check_drops(bus)
            stop = self.runtime.pipeline.excitation.stop(self.runtime.pipeline.t_s)
            if stop is not None:
                try:
                    for ident, data in self.runtime.frames([stop]):
                        bus.send(ident, data)
                except BusError:
                    pass
            self.notifier.stopping()
            bus.close()
            self.runtime.pipeline.worker.close()
            self._close_telemetry()
        saved = self.save(final=True)
        c = self.runtime.pipeline.counters
        self.say(f"stopped: {self.runtime.frames_in} frames in, {self.runtime.frames_out} frames out, "
                 f"{c.samples} samples, {c.bad_frames} bad frames, {c.missing_frames} missing frames, "
                 f"{self.runtime.pipeline.dropped_frames} dropped by the kernel, "
                 f"{c.faults[FrameFault.UNKNOWN_ID]} foreign frames, {self._commands_text()}, "
                 f"state {self.runtime.pipeline.state.name}; "
                 f"{self.reaction.summary()}"
                 + (f" (the loop's own work on the frame: {self.processing.summary('processing')}; "
                    f"its CPU time: {self.processing_cpu.summary('processing CPU')})"
                    if self.processing.n else ""))
        if self.processing.n:
            self.say("the loop on a frame that publishes, by phase: "
                     + "; ".join(times.summary(what) for what, times in self.phases.items()))
        if not saved:  # systemd sees it: the state on disk is older than the service's
            self.say(f"exit status 1: the last save of the state failed ({self.state_file})")
            return 1
        return 0


def run_service(settings: Settings, max_s: float | None = None) -> int:
    """Run the daemon until SIGTERM/SIGINT (or ``max_s``); returns the exit status."""
    service = Service(settings)
    # What start-up made (modules, compiled code, the restored state: about 190,000 objects) is moved out of
    # the collector's reach: a full collection scanned it all, 80-300 ms in which no frame is read.
    gc.collect()
    gc.freeze()
    signal.signal(signal.SIGTERM, service.request_stop)
    signal.signal(signal.SIGINT, service.request_stop)
    return service.run(max_s=max_s)
