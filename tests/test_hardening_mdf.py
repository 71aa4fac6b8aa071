"""Corrupt MDF 4 files: one line on stderr, exit status 2, no traceback, whatever asammdf raises.

asammdf's ``MDF4.__del__`` fails on an object its constructor left half-built; the error must not keep
that object alive past the point where its noise is silenced (it printed a traceback at the interpreter's
exit). So the commands run in a child interpreter, and the whole of its stderr is checked, the exit
included.
"""

import random
import subprocess
import sys
import textwrap

import pytest

from online_id.cli import main

TINY = "operating_points: [{speed_rpm: 1200, duration_s: 2}]\nseed: 3\n"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("mdf_bad")
    (d / "bench.yaml").write_text(TINY)
    assert main(["simulate", "--config", str(d / "bench.yaml"), "--out", str(d / "sig.mf4"),
                 "--can-log", str(d / "can.mf4"), "--quiet"]) == 0
    return d


def _corruptions(raw: bytes, seed: int) -> dict[str, bytes]:
    """Cut at several lengths, and bits flipped in the header blocks and all over the file."""
    rng = random.Random(seed)
    out = {f"cut{frac}": raw[: int(len(raw) * frac)] for frac in (0.002, 0.05, 0.5, 0.98)}
    for name, lo, hi in (("flip_id", 0, 64), ("flip_head", 64, 2000), ("flip_any", 64, len(raw))):
        b = bytearray(raw)
        for _ in range(30):
            b[rng.randrange(lo, hi)] ^= 1 << rng.randrange(8)
        out[name] = bytes(b)
    return out


def _run_all(argvs: list[list[str]]) -> tuple[list[int], str]:
    """``online-id`` on each argv in one child interpreter: the statuses and all of its stderr.

    A collection after each command stands for the interpreter's exit: what a command left for the
    collector (a half-built asammdf object) is collected there, with Python's own report of errors."""
    code = textwrap.dedent(f"""
        import gc
        from online_id.cli import main
        rcs = []
        for argv in {argvs!r}:
            rcs.append(main(argv))
            gc.collect()
        print(rcs)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240)
    return eval(proc.stdout.strip().splitlines()[-1]), proc.stderr  # noqa: S307 - our own child's list


@pytest.mark.parametrize("kind", ["sig", "can"])
def test_corrupt_mf4_gives_one_line_and_no_traceback(recordings, kind):
    raw = (recordings / f"{kind}.mf4").read_bytes()
    argvs = []
    for name, data in _corruptions(raw, seed=len(raw)).items():
        path = recordings / f"{kind}_{name}.mf4"
        path.write_bytes(data)
        if kind == "sig":
            argvs.append(["identify", str(path)])
        else:
            argvs += [["replay", str(path)], ["convert", str(path), str(recordings / f"{name}.csv")]]
    rcs, err = _run_all(argvs)
    assert "Traceback" not in err and "Exception ignored" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    failed = [a for a, rc in zip(argvs, rcs) if rc != 0]
    # every cut file fails; a bit flipped in the samples alone may still read (the values then tell)
    assert all(rc in (0, 2) for rc in rcs)
    assert sum(rc == 2 for rc in rcs) >= len(argvs) - (1 if kind == "sig" else 2)
    errors = [line for line in lines if line.startswith("error: ")]
    assert len(errors) == len(failed), err
    for argv, line in zip(failed, errors):
        assert argv[1].rsplit("/", 1)[-1] in line
