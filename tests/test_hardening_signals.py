"""SIGTERM and SIGINT at any moment, start-up included: nothing left behind, no traceback, the documented status.

A real ``online-id`` child process gets the signal: while its modules load, while it simulates, while it
writes its outputs; then its directory holds no partial file and every output it holds is whole (equal to
the one of an uninterrupted run), stderr holds at most the one line ``interrupted by SIGTERM``, and the
status is 143 for SIGTERM, 130 for SIGINT (0 if it finished first). The service (``run``) stops with 0.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SCENARIO = "operating_points: [{speed_rpm: 1300, duration_s: 12}, {speed_rpm: 1800, duration_s: 12}]\nseed: 4\n"
OUTPUTS = ("b.csv", "b.truth.json", "b.blf")
STATUS = {signal.SIGTERM: 143, signal.SIGINT: 130}


def _spawn(directory: Path, *argv: str) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "online_id", *argv], cwd=directory, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _simulate(directory: Path) -> subprocess.Popen:
    (directory / "s.yaml").write_text(SCENARIO)
    return _spawn(directory, "simulate", "--config", "s.yaml", "--out", "b.csv", "--can-log", "b.blf", "--quiet")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The outputs of an uninterrupted run, and how long it took."""
    d = tmp_path_factory.mktemp("sig_ref")
    t0 = time.monotonic()
    proc = _simulate(d)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    return {name: (d / name).read_bytes() for name in OUTPUTS}, time.monotonic() - t0


def _check(directory: Path, proc: subprocess.Popen, sig: int, reference: dict) -> str:
    out, err = proc.communicate(timeout=120)
    left = sorted(p.name for p in directory.iterdir() if p.name not in ("s.yaml", *OUTPUTS))
    assert not left, f"left behind: {left}"
    for name in OUTPUTS:
        if (directory / name).exists():
            assert (directory / name).read_bytes() == reference[name], f"{name} is not whole"
    assert "Traceback" not in err and "Exception" not in err, err
    if proc.returncode == 0:  # it finished before the signal came
        assert all((directory / name).exists() for name in OUTPUTS)
        return "finished"
    assert proc.returncode == STATUS[sig], (proc.returncode, err)
    assert err.strip() == f"interrupted by {signal.Signals(sig).name}", err
    return "interrupted"


def _wait_for_partial(directory: Path, proc: subprocess.Popen, timeout_s: float = 120.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and proc.poll() is None:
        if any(".partial" in p.name for p in directory.iterdir()):
            return True
        time.sleep(0.002)
    return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_while_the_outputs_are_written_leaves_nothing(tmp_path, reference, sig):
    proc = _simulate(tmp_path)
    assert _wait_for_partial(tmp_path, proc)  # the outputs are being written under temporary names
    proc.send_signal(sig)
    assert _check(tmp_path, proc, sig, reference[0]) == "interrupted"
    assert not any((tmp_path / name).exists() for name in OUTPUTS)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_while_the_modules_load_gives_one_line(tmp_path, reference, sig):
    proc = _simulate(tmp_path)
    time.sleep(0.5)  # past the interpreter's start, in the import of numpy, scipy, numba ...
    proc.send_signal(sig)
    assert _check(tmp_path, proc, sig, reference[0]) == "interrupted"


def test_sigterm_before_online_id_runs_leaves_nothing(tmp_path, reference):
    """In the interpreter's own start-up SIGTERM is Python's: the process ends by the signal, at once."""
    proc = _simulate(tmp_path)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode in (-signal.SIGTERM, 143) and "Traceback" not in err
    assert [p.name for p in tmp_path.iterdir()] == ["s.yaml"]


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_at_any_moment_of_a_run(tmp_path, reference, sig):
    outputs, duration_s = reference
    seen = set()
    for k, frac in enumerate((0.15, 0.3, 0.45, 0.6, 0.75, 0.9)):
        d = tmp_path / f"at{k}"
        d.mkdir()
        proc = _simulate(d)
        time.sleep(frac * duration_s)
        proc.send_signal(sig)
        seen.add(_check(d, proc, sig, outputs))
    assert "interrupted" in seen


def _stop_service(directory: Path, in_loop: bool) -> str:
    proc = _spawn(directory, "run", "--interface", "virtual", "--channel", f"sig-{os.getpid()}-{in_loop}",
                  "--max-seconds", "120")
    if in_loop:
        end = time.monotonic() + 120
        line = ""
        while "listening" not in line and time.monotonic() < end:
            line = proc.stderr.readline()
    else:
        time.sleep(0.8)  # loading its modules
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err
    assert [p.name for p in directory.iterdir()] == []
    return err


def test_the_service_stops_with_status_0_in_its_start_up(tmp_path):
    err = _stop_service(tmp_path, in_loop=False)
    assert err.strip() == "online-id: stopped by SIGTERM during start-up", err


@pytest.mark.slow
def test_the_service_stops_with_status_0_in_its_loop(tmp_path):
    assert "online-id: stopped:" in _stop_service(tmp_path, in_loop=True)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_that_a_library_turned_into_its_own_error_is_still_a_stop(monkeypatch, capsys, sig):
    """A signal that cuts an extension module's import short can come out as that module's own error
    (numpy's ImportError when ``datetime`` did not load): one line and the signal's status, no traceback."""
    from online_id import cli

    def build_parser(command=None):
        try:
            os.kill(os.getpid(), sig)
            time.sleep(5)
        except KeyboardInterrupt as err:
            raise ImportError("numpy: PyCapsule_Import could not import module 'datetime'") from err
        raise AssertionError("no stop arrived")

    monkeypatch.setattr(cli, "build_parser", build_parser)
    assert cli.main(["simulate"]) == STATUS[sig]
    assert capsys.readouterr().err.strip() == f"interrupted by {signal.Signals(sig).name}"


def test_an_error_without_a_stop_is_not_taken_for_one(monkeypatch):
    from online_id import cli

    def build_parser(command=None):
        raise ImportError("a missing module")

    monkeypatch.setattr(cli, "build_parser", build_parser)
    with pytest.raises(ImportError, match="a missing module"):
        cli.main(["simulate"])


def test_the_console_process_ends_after_a_stop_without_finalisation_but_with_its_exit_functions(tmp_path):
    """After a stop the console process skips the interpreter's finalisation (what the signal cut short
    half-made can crash it there: SIGSEGV instead of the status), yet its atexit functions run and what
    it printed reaches the reader."""
    marker = tmp_path / "atexit-ran"
    code = (
        "import atexit, sys\n"
        "from online_id.interrupt import end_process\n"
        f"atexit.register(lambda: open({str(marker)!r}, 'w').close())\n"
        "class Crash:\n"
        "    def __del__(self):\n"
        "        print('finalised', file=sys.stderr)\n"
        "keep = Crash()\n"
        "print('said before the end', end='')\n"
        "end_process(130)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130
    assert proc.stdout == "said before the end"
    assert "finalised" not in proc.stderr
    assert marker.exists()
