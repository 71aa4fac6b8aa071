"""CAN log files: candump ``.log``, Vector ``.asc``, ``.blf`` and MDF 4 bus logging ``.mf4`` through python-can.

Frames are plain tuples so that nothing outside :mod:`online_id.io` sees a
python-can object: :func:`write_log` takes ``(t_s, arbitration_id, data)``
(optionally a fourth item ``is_extended``), :func:`read_log` yields
``(t_s, arbitration_id, data, is_extended, is_error_frame)``.

Timestamps are written as given and read back as the file holds them:
``.log`` keeps absolute seconds (1 us resolution); ``.asc`` stores times
relative to its first frame (1 us), so they come back shifted by the first
frame's time; ``.blf`` keeps nanoseconds relative to a start time that is only
stored for Unix timestamps (times before 1990 come back as written); ``.mf4``
(python-can's ``MF4Writer``/``MF4Reader``, ASAM MDF bus logging through
asammdf) keeps times relative to the measurement's start time.  A ``.mf4``
that holds signals rather than CAN frames is refused with a note on what reads
it (:mod:`online_id.io.mdf`).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import can
import numpy as np

from online_id.errors import InputDataError
from online_id.io.logformats import SUFFIXES  # noqa: F401 - the formats write_log and read_log support
from online_id.io.outfile import atomic_output

Frame = tuple[float, int, bytes]
LoggedFrame = tuple[float, int, bytes, bool, bool]


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputDataError(
            f"{path}: expected a CAN log with suffix {', '.join(SUFFIXES)}, but got {path.suffix or 'no suffix'!r}"
        )
    return suffix


def _writer(path: Path, suffix: str, channel: str) -> can.io.generic.MessageWriter:
    if suffix == ".log":
        return can.CanutilsLogWriter(path, channel=channel)
    if suffix == ".asc":
        return can.ASCWriter(path)
    if suffix == ".mf4":
        return BufferedMF4Writer(path)
    return can.BLFWriter(path)


class BufferedMF4Writer(can.io.MF4Writer):
    """python-can's ``MF4Writer``, its classic data frames handed to asammdf ``CHUNK`` at a time.

    ``MF4Writer`` extends the file by one frame per call, and asammdf writes
    a data block for each: 66,000 frames (22 s of a bench) took 21 s of CPU
    and 270 s of wall time.  The file is the same (same groups, channels and
    values); remote, error and CAN FD frames go through ``MF4Writer`` itself.
    """

    CHUNK = 20_000

    def __init__(self, file, **kwargs) -> None:
        super().__init__(file, **kwargs)
        self._times: list[float] = []
        self._rows: list[tuple] = []

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            self._flush()
            super().on_message_received(msg)
            return
        t = msg.timestamp
        if t is None:
            t = self.last_timestamp
        else:
            self.last_timestamp = max(self.last_timestamp, t)
        self._times.append(t - self._start_time)
        self._rows.append((msg.channel, msg.arbitration_id, msg.is_extended_id, msg.is_rx, bytes(msg.data), msg.dlc))
        if len(self._times) >= self.CHUNK:
            self._flush()

    def _flush(self) -> None:
        if not self._times:
            return
        from can.io.mf4 import STD_DTYPE
        from can.util import channel2int

        buf = np.zeros(len(self._times), dtype=STD_DTYPE)
        data = buf["CAN_DataFrame.DataBytes"]
        for k, (channel, ident, ext, rx, payload, dlc) in enumerate(self._rows):
            ch = channel2int(channel)
            if ch is not None:
                buf["CAN_DataFrame.BusChannel"][k] = ch
            buf["CAN_DataFrame.ID"][k] = ident
            buf["CAN_DataFrame.IDE"][k] = int(ext)
            buf["CAN_DataFrame.Dir"][k] = 0 if rx else 1
            buf["CAN_DataFrame.DataLength"][k] = len(payload)
            buf["CAN_DataFrame.DLC"][k] = dlc
            data[k, :len(payload)] = np.frombuffer(payload, dtype=np.uint8)
        self._mdf.extend(0, [(np.asarray(self._times, dtype="<f8"), None), (buf, None)])
        self._times, self._rows = [], []

    def stop(self) -> None:
        self._flush()
        super().stop()


def write_log(path: str | Path, frames: Iterable[tuple], channel: str = "can0") -> int:
    """Write frames ``(t_s, arbitration_id, data[, is_extended])`` to a CAN log; returns the count.

    The format follows the suffix: ``.log`` (``candump -l``), ``.asc`` or ``.blf``.
    Without the fourth item an ID above 0x7FF is written as extended.

    Raises
    ------
    InputDataError
        Unknown suffix, or the file cannot be written (names the file).
    """
    path = Path(path)
    suffix = _suffix(path)
    count = 0
    with atomic_output(path) as tmp:  # no half-written log: a temporary name, renamed on success
        try:
            writer = _writer(tmp, suffix, channel)
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
        try:
            for frame in frames:
                t_s, arbitration_id, data = frame[0], int(frame[1]), bytes(frame[2])
                extended = bool(frame[3]) if len(frame) > 3 else arbitration_id > 0x7FF
                writer.on_message_received(can.Message(
                    timestamp=float(t_s), arbitration_id=arbitration_id, is_extended_id=extended,
                    data=data, dlc=len(data), is_rx=True, channel=channel,
                ))
                count += 1
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
        finally:
            try:
                writer.stop()  # flushes: a full disk shows here (.blf)
            except OSError as err:
                raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
    return count


def count_frames(path: str | Path) -> int | None:
    """About how many frames the log holds (for a progress bar), cheaply; None when it cannot tell.

    ``.log``: its lines; ``.asc``: its lines (a few header lines too many);
    ``.blf``: the object count of its header; ``.mf4``: the cycles of its CAN
    channel groups.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in (".log", ".asc"):
            with path.open("rb") as raw:
                return sum(block.count(b"\n") for block in iter(lambda: raw.read(1 << 22), b""))
        if suffix == ".blf":
            reader = can.BLFReader(path)
            reader.stop()
            return int(reader.object_count) or None
        if suffix == ".mf4":
            from asammdf import MDF

            from online_id.io.mdf import _quiet, opened

            with _quiet():
                mdf = opened(lambda: MDF(path), path)
                try:
                    return sum(int(g.channel_group.cycles_nr) for g in mdf.groups
                               if any(ch.name.startswith("CAN_") for ch in g.channels)) or None
                finally:
                    mdf.close()
    except Exception:  # only a hint: the reading proper reports what is wrong with the file
        return None
    return None


_READ_ERRORS = (OSError, ValueError, EOFError, IndexError, KeyError, struct.error, zlib.error,
                can.io.blf.BLFParseError)


def _bad_line(path: Path, frames_read: int) -> int | None:
    """Line number of the (frames_read + 1)-th non-blank line of a candump log."""
    try:
        with path.open("r", encoding="utf-8", errors="replace") as handle:
            seen = 0
            for number, line in enumerate(handle, start=1):
                if line.strip():
                    if seen == frames_read:
                        return number
                    seen += 1
    except OSError:
        return None
    return None


def _tail(path: Path, n: int = 256) -> bytes:
    with path.open("rb") as fh:
        fh.seek(0, 2)
        size = fh.tell()
        fh.seek(max(0, size - n))
        return fh.read()


def _cut_text_log(path: Path, suffix: str) -> str | None:
    """Why a text log looks cut short (None: it looks whole)."""
    tail = _tail(path)
    if not tail:
        return None
    if suffix == ".log" and not tail.endswith(b"\n"):
        return "its last line is incomplete"
    if suffix == ".asc" and b"End TriggerBlock" not in tail:
        return 'no "End TriggerBlock" at its end'
    return None


def _cut_note(path: Path, cut: str, count: int) -> str:
    return f"{path}: warning: the log ends early ({cut}); used the {count} frames before the cut"


def read_log(path: str | Path, on_truncated: Callable[[str], None] | None = None) -> Iterator[LoggedFrame]:
    """Frames ``(t_s, arbitration_id, data, is_extended, is_error_frame)`` of a CAN log.

    A log that ends early (a copy cut short, a logger that died) is read up
    to the cut: the frames before it are yielded (an incomplete last line of
    a ``.log`` is not), and ``on_truncated`` gets one line saying so, with the
    number of frames read, after the last frame.

    Raises
    ------
    InputDataError
        Unknown suffix, missing or corrupt file; names the file (and, for
        ``.log``, the line).
    """
    path = Path(path)
    suffix = _suffix(path)
    if path.is_dir():
        raise InputDataError(f"{path}: cannot read the CAN log: it is a directory")
    if not path.is_file():
        raise InputDataError(f"{path}: cannot read the CAN log: no such file")
    count = 0
    if suffix == ".mf4":
        yield from _read_mf4(path)
        return
    try:
        cut = _cut_text_log(path, suffix) if suffix != ".blf" else None
        reader = can.LogReader(path)
    except _READ_ERRORS as err:
        raise InputDataError(f"{path}: cannot read the CAN log: {err}") from err
    try:
        held = None  # one frame of look-ahead: the last line of a cut .log is not used
        for msg in reader:
            data = b"" if msg.is_remote_frame or msg.data is None else bytes(msg.data)
            frame = (float(msg.timestamp), int(msg.arbitration_id), data, bool(msg.is_extended_id),
                     bool(msg.is_error_frame))
            if held is not None:
                yield held
                count += 1
            held = frame
        if held is not None and not (cut and suffix == ".log"):
            yield held
            count += 1
        if suffix == ".blf":
            expected = int(getattr(reader, "object_count", 0) or 0)
            if count < expected or path.stat().st_size < int(getattr(reader, "file_size", 0) or 0):
                cut = f"{count} of the {expected} objects its header announces"
    except _READ_ERRORS as err:
        line = _bad_line(path, count + (held is not None)) if suffix == ".log" else None
        if cut and suffix == ".log" and line is not None and _bad_line(path, count + 1 + (held is not None)) is None:
            # the incomplete last line of a cut log: the frames before it are used
            if held is not None:
                yield held
                count += 1
            if on_truncated is not None:
                on_truncated(_cut_note(path, cut, count))
            return
        where = f"{path}:{line}" if line else f"{path}: after {count} frames"
        text = " ".join(str(err).split()) or type(err).__name__
        raise InputDataError(f"{where}: corrupt {suffix} CAN log: {text}") from err
    finally:
        reader.stop()
    if cut and on_truncated is not None:
        on_truncated(_cut_note(path, cut, count))


def _read_mf4(path: Path) -> Iterator[LoggedFrame]:
    """Frames of an MDF 4 bus logging file (python-can's ``MF4Reader``); one-line errors for bad files."""
    from online_id.io.mdf import _quiet, is_bus_log, opened, read_error

    if not is_bus_log(path):
        raise InputDataError(f"{path}: an MDF 4 signal recording, not CAN bus logging (no CAN_DataFrame "
                             f"channel group); identify and diagnose read its channels")
    with _quiet():
        reader = opened(lambda: can.io.MF4Reader(path), path, "CAN log")
        messages = opened(lambda: iter(reader), path, "CAN log")
    count = 0
    try:
        for msg in messages:
            data = b"" if msg.is_remote_frame or msg.data is None else bytes(msg.data)
            yield (float(msg.timestamp), int(msg.arbitration_id), data, bool(msg.is_extended_id),
                   bool(msg.is_error_frame))
            count += 1
    except Exception as err:  # a data block cut short or corrupt (asammdf raises many kinds)
        raise InputDataError(f"{read_error(path, err, 'CAN log')} (after {count} frames)") from None
    finally:
        reader.stop()
