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
def test_systemd_analyze_verify(tmp_path):
    exe = Path(sys.executable).parent / "online-id"
    if not exe.exists():
        pytest.skip("the online-id console script is not installed next to this Python")
    text = (DEPLOY / "online-id.service").read_text().replace("/opt/online-id/venv/bin/online-id", str(exe))
    unit = tmp_path / "online-id.service"
    unit.write_text(text)
    res = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "online-id.service" not in res.stderr, res.stderr  # no warnings about our unit
