"""A CAN log through exactly the pipeline of the live service: the runtime that keeps its publications, the
replay loop, the service's state loaded and kept, and the publications as MDF 4 channel groups."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from online_id.errors import EstimationError, InputDataError
from online_id.io.canlog import count_frames, read_log
from online_id.io.outfile import check_output
from online_id.io.statefile import load_state, save_state
from online_id.progress import Progress
from online_id.records import AlertKind, AlertOut, EstimateOut, ExcitationOut, FrameFault, Publication, QualityOut, \
    ServiceState, StatusOut
from online_id.service.runtime import OutFrame, Runtime


class ResultsRuntime(Runtime):
    """A :class:`~online_id.service.runtime.Runtime` that keeps every publication with the engine speed at that moment."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.published: list[tuple[Publication, float]] = []

    def frames(self, pubs: list[Publication]) -> list[OutFrame]:
        speed = self.pipeline.estimator.speed_rpm
        self.published += [(pub, speed) for pub in pubs]
        return super().frames(pubs)


def results_groups(published: list[tuple[Publication, float]], base, alerts: list[AlertOut] | None = None) -> list:
    """The MDF 4 channel groups of the service's publications (:mod:`online_id.io.mdf_results`).

    ``alerts`` replaces the alerts among ``published`` (e.g. the pipeline's
    own list, without the repeats of a latched alarm).
    """
    from online_id.io.mdf_results import Channel, ChannelGroup

    def of(kind):
        return [(p, n) for p, n in published if isinstance(p, kind)]

    est, qual, stat, exc = of(EstimateOut), of(QualityOut), of(StatusOut), of(ExcitationOut)
    alert_list = [p for p, _ in of(AlertOut)] if alerts is None else list(alerts)
    states = {int(s): s.name for s in ServiceState}
    kinds = {int(k): k.name for k in AlertKind}
    return [
        ChannelGroup("online-id estimate", base.rel([p.t_s for p, _ in est]), [
            Channel("oid_f0", [p.f0_hz for p, _ in est], "Hz", "driveline resonance frequency"),
            Channel("oid_zeta", [p.zeta for p, _ in est], "", "driveline damping ratio"),
            Channel("oid_c_s", [p.c_s for p, _ in est], "Nm/rad", "shaft stiffness"),
            Channel("oid_d_s", [p.d_s for p, _ in est], "Nm s/rad", "shaft damping"),
            Channel("oid_valid", [int(p.valid) for p, _ in est], "", "estimate valid", {0: "invalid", 1: "valid"}),
            Channel("oid_engine_speed", [n for _, n in est], "rpm", "engine speed of the estimator at the estimate"),
        ], "the published driveline estimates"),
        ChannelGroup("online-id quality", base.rel([p.t_s for p, _ in qual]), [
            Channel("oid_residual_rms", [p.residual_rms for p, _ in qual], "rad/s",
                    "RMS of the one-step prediction error of the dyno speed"),
            Channel("oid_fpe", [p.fpe for p, _ in qual], "rad/s", "square root of the final prediction error"),
            Channel("oid_excitation_rms", [p.excitation for p, _ in qual], "Nm", "RMS of the torque excitation"),
            Channel("oid_samples_used", [p.samples_used for p, _ in qual], "", "samples in the estimate"),
        ], "the published model quality"),
        ChannelGroup("online-id status", base.rel([p.t_s for p, _ in stat]), [
            Channel("oid_state", [int(p.state) for p, _ in stat], "", "health state of the service", states),
            Channel("oid_bad_frames", [p.bad_frames for p, _ in stat], "", "bad input frames so far"),
            Channel("oid_missing_frames", [p.missing_frames for p, _ in stat], "", "missing input frames so far"),
        ], "the published health state"),
        ChannelGroup("online-id alert", base.rel([a.t_s for a in alert_list]), [
            Channel("oid_alert_kind", [int(a.kind) for a in alert_list], "", "kind of alert", kinds),
            Channel("oid_alert_severity", [int(a.severity) for a in alert_list], "", "severity",
                    {0: "info", 1: "warning", 2: "fault"}),
            Channel("oid_alert_change", [a.value_pct for a in alert_list], "%", "change against the baseline"),
            Channel("oid_alert_speed", [a.speed_rpm for a in alert_list], "rpm", "engine speed at the alert"),
            Channel("oid_alert_message", [a.message or "-" for a in alert_list], "", "the alert's message"),
        ], "the alerts raised"),
        ChannelGroup("online-id excitation", base.rel([p.t_s for p, _ in exc]), [
            Channel("oid_prbs_offset", [p.torque_offset_nm for p, _ in exc], "Nm", "PRBS torque offset requested"),
            Channel("oid_prbs_active", [int(p.active) for p, _ in exc], "", "PRBS active", {0: "off", 1: "on"}),
        ], "the requested test torque"),
    ]


def write_results(path: str, log: str, runtime: ResultsRuntime, alerts: list[AlertOut] | None = None) -> None:
    """``--out-mf4``: the publications of a replay of ``log`` as MDF 4 channels on the log's time base."""
    from online_id.io.mdf_results import recording_time_base, write_results_mdf

    base = recording_time_base(log, runtime.pipeline.t_first)
    write_results_mdf(path, results_groups(runtime.published, base, alerts), base,
                      comment=f"online-id results of {Path(log).name}")


def state_file(directory: Path) -> Path:
    """The state file in ``directory`` (the name the live service uses)."""
    from online_id.service.live import STATE_FILE

    if directory.exists() and not directory.is_dir():
        raise InputDataError(f"{directory}: --state expects a directory, but this is a file")
    check_output(directory, "state", directory=True)  # before the replay, not after it
    return directory / STATE_FILE


def restore(runtime: Runtime, path: Path) -> bool:
    """Load a saved state as an earlier run's into ``runtime``'s pipeline; False if there is none yet."""
    state = load_state(path)
    if state is None:
        return False
    try:
        runtime.pipeline.load_state(state, new_run=True)
    except (EstimationError, KeyError, TypeError, ValueError) as err:
        raise InputDataError(f"{path}: not a state of this version of online-id ({err})") from None
    return True


def keep(runtime: Runtime, path: Path) -> None:
    """Save the pipeline's state to ``path`` (atomically); an unwritable place is a one-line error."""
    try:
        save_state(path, runtime.pipeline.get_state())
    except OSError as err:
        raise InputDataError(f"{path}: cannot save the state ({err.strerror or err})") from None


def replay(path: str, runtime: Runtime, realtime: bool = False, progress: Progress | None = None,
           require_match: bool = False) -> int:
    """Feed every frame of the log; returns the number of frames published.

    Raises :class:`InputDataError` when the log holds no frame, or (with
    ``require_match``) none of an ID the config maps; a log that ends early
    is used up to the cut, with a warning on stderr.
    """
    published = 0
    t_first = None
    wall0 = time.monotonic()
    cut: list[str] = []
    total = count_frames(path) if progress is not None and progress.enabled else None
    ids: set[int] = set()
    for k, (t_s, ident, data, is_ext, is_err) in enumerate(read_log(path, cut.append)):
        ids.add(ident)
        if t_first is None:
            t_first = t_s
        if realtime:
            delay = (t_s - t_first) - (time.monotonic() - wall0)
            if delay > 0:
                time.sleep(delay)
        published += len(runtime.on_frame(t_s, ident, data, is_ext, is_err))
        if progress is not None and k % 2000 == 0:
            progress.count(k, total, f"t = {t_s - t_first:.1f} s")
    if t_first is None:
        raise InputDataError(f"{path}: no CAN frames in the log" + (" (it ends early)" if cut else ""))
    if require_match and runtime.pipeline.counters.faults[FrameFault.UNKNOWN_ID] == runtime.frames_in:
        raise InputDataError(no_match(path, runtime, ids))
    for text in cut:
        print(text, file=sys.stderr)
    published += len(runtime.tick(runtime.pipeline.t_s))
    return published


def no_match(path: str, runtime: Runtime, ids: set[int]) -> str:
    """The error for a log none of whose frames has an ID the config maps."""
    wanted = ", ".join(f"0x{fid:X}" for fid in sorted(runtime.decoder.frame_ids))
    seen = sorted(ids)
    shown = ", ".join(f"0x{fid:X}" for fid in seen[:8]) + (f" and {len(seen) - 8} more" if len(seen) > 8 else "")
    return (f"{path}: none of its {runtime.frames_in} frames has an ID the config maps ({wanted}; "
            f"{runtime.decoder.source}, config keys dbc and mapping); the log holds IDs {shown}")
