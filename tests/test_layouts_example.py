"""The worked example of docs/measured-rigs.md, run as documented: a two-logger rig with degree encoders on
one clock, simulated and diagnosed by the page's two commands through ``online_id.cli.main``."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import numpy as np
import pytest

from online_id.cli import main

DOC = Path(__file__).resolve().parent.parent / "docs" / "measured-rigs.md"


def documented_commands() -> list[list[str]]:
    """The commands of the page's first ``sh`` block (continuation lines joined, redirections dropped)."""
    text = DOC.read_text(encoding="utf-8")
    block = text.split("```sh\n", 1)[1].split("```", 1)[0].replace("\\\n", " ")
    out = []
    for line in block.splitlines():
        words = shlex.split(line)
        if words and words[0] == "online-id":
            out.append(words[1:words.index(">")] if ">" in words else words[1:])
    return out


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """Run the page's commands in a fresh directory; return the truth and the diagnosis JSON."""
    import contextlib
    import io
    import os

    d = tmp_path_factory.mktemp("measured-rig")
    simulate, diagnose = documented_commands()
    assert simulate[0] == "simulate-rig" and diagnose[0] == "diagnose"
    here = os.getcwd()
    os.chdir(d)
    try:
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out):
            assert main(simulate) == 0
        truth = json.loads(out.getvalue())
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            assert main(diagnose + ["--json"]) == 0
    finally:
        os.chdir(here)
    return truth, json.loads(out.getvalue()), err.getvalue()


@pytest.mark.slow
def test_documented_command_reads_the_two_logger_layout(example):
    truth, doc, err = example
    rec = doc["recording"]
    # files and clock: one clock as stated, nothing estimated, the sensor logger's late start cut away
    assert rec["clock"]["mode"] == "same" and not rec["clock"]["estimated"]
    assert "nothing estimated" in err and "warning" not in err.replace("warning: one operating point", "")
    lay = rec["layout"]
    assert lay["t0_s"] == pytest.approx(truth["sensor_start_s"], abs=2e-3)
    assert "drive.csv" in lay["input"] and "sensor.csv" in lay["output"]
    # units: degrees as given; speeds as the truth's (the motor within 0.1 %), the gear rates exact
    rpm = truth["motor_speed_rpm"][0]
    shafts = lay["shafts"]
    assert all(s["unit"] == "deg" for s in shafts.values())
    assert shafts["motor"]["mean_rpm"] == pytest.approx(rpm, rel=1e-3)
    assert shafts["load"]["mean_rpm"] == pytest.approx(rpm / 12, rel=1e-3)
    assert doc["shaft_rates"] == pytest.approx({"motor": 1, "stage1": 1 / 3, "shaft1": 1 / 3, "stage2": 1 / 12,
                                                "load": 1 / 12})
    # speeds at full rate, decimated alike afterwards; the output is the motor speed in rad/s
    assert rec["data_path"]["fs_in_hz"] == pytest.approx(1000.0, rel=1e-3) and rec["data_path"]["decimation"] == 4
    assert doc["output"] == "dencoder1/dt" and "twist" in lay["torsion"]
    assert np.isfinite(doc["error_before"]["rms"]) and doc["error_before"]["rms"] < 0.01 * rpm * np.pi / 30


@pytest.mark.slow
def test_documented_command_names_the_once_per_revolution_line(example):
    truth, doc, _ = example
    assert (truth["disturbance"]["shaft"], truth["disturbance"]["order"]) == ("motor", 1.0)
    assert doc["effects"], "nothing named"
    first = doc["effects"][0]
    assert first["kind"] == "rotation_order_disturbance", first
    assert (first["params"]["shaft"], first["params"]["order"]) == ("motor", 1)
