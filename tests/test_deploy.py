"""Deployment files: the systemd unit verifies, the example config loads."""

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from online_id.config import load_config

DEPLOY = Path(__file__).parent.parent / "deploy"


def test_example_config_is_valid():
    s = load_config(DEPLOY / "config.yaml")
    assert s.bus.interface == "socketcan" and s.excitation.enabled is False


def test_unit_has_the_required_settings():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(DEPLOY / "online-id.service")
    svc = unit["Service"]
    assert svc["Type"] == "notify"
    assert svc["Restart"] == "on-failure"
    assert svc["DynamicUser"] == "yes"
    assert svc["StateDirectory"] == "online-id" and svc["ConfigurationDirectory"] == "online-id"
    assert svc["RestrictAddressFamilies"].split() == ["AF_CAN", "AF_UNIX"]
    assert svc["CapabilityBoundingSet"] == ""
    assert "WatchdogSec" in svc and "run --config" in svc["ExecStart"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
@pytest.mark.parametrize("dropin", [None, *sorted(p.name for p in (DEPLOY / "online-id.service.d").glob("*.conf"))])
def test_systemd_analyze_verify(tmp_path, dropin):
    """The unit, alone and with each drop-in (its sections appended, as systemd merges them), verifies."""
    exe = Path(sys.executable).parent / "online-id"
    if not exe.exists():
        pytest.skip("the online-id console script is not installed next to this Python")
    text = (DEPLOY / "online-id.service").read_text().replace("/opt/online-id/venv/bin/online-id", str(exe))
    if dropin is not None:
        text += "\n" + (DEPLOY / "online-id.service.d" / dropin).read_text()
    unit = tmp_path / "online-id.service"
    unit.write_text(text)
    res = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "online-id.service" not in res.stderr, res.stderr  # no warnings about our unit


def test_realtime_dropin_lifts_the_units_restriction():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(DEPLOY / "online-id.service.d" / "realtime.conf")
    svc = unit["Service"]
    assert svc["CPUSchedulingPolicy"] == "fifo" and 1 <= int(svc["CPUSchedulingPriority"]) <= 99
    assert svc["RestrictRealtime"] == "no"  # the unit's RestrictRealtime=yes would refuse the policy
