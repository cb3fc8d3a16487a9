"""The deployment files: the agent's systemd unit lets it open the usual serial autopilots."""

from __future__ import annotations

import configparser
import subprocess
from pathlib import Path

import pytest

from tests.support.paths import ROOT


def unit(name: str) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read_string((ROOT / "deploy" / name).read_text())
    return parser


def allowed_devices() -> set[str]:
    """Every DeviceAllow= entry (systemd keeps each repeated line, configparser only the last)."""
    lines = (ROOT / "deploy" / "fleetgcs-agent.service").read_text().splitlines()
    return {line.split("=", 1)[1].split()[0] for line in lines if line.startswith("DeviceAllow=")}


@pytest.mark.parametrize(
    ("device", "entry"),
    [
        ("/dev/serial0", "/dev/serial0"),
        ("/dev/ttyAMA0", "char-ttyAMA"),
        ("/dev/ttyS0", "char-ttyS"),
        ("/dev/ttyACM0", "char-ttyACM"),
        ("/dev/ttyUSB1", "char-ttyUSB"),
    ],
)
def test_agent_unit_allows_the_usual_serial_devices(device: str, entry: str) -> None:
    assert entry in allowed_devices(), f"{device} needs DeviceAllow={entry} rw"
    service = unit("fleetgcs-agent.service")["Service"]
    assert "dialout" in (service["Group"], service["SupplementaryGroups"])


def test_unit_files_verify_where_systemd_is_present(tmp_path: Path) -> None:
    check = subprocess.run(["which", "systemd-analyze"], capture_output=True, text=True)
    if check.returncode != 0:
        pytest.skip("systemd-analyze is not installed here")
    for name in ("fleetgcs-agent.service", "fleetgcs-gcs.service"):
        result = subprocess.run(
            ["systemd-analyze", "verify", "--man=no", ROOT / "deploy" / name],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        problems = [
            line for line in result.stderr.splitlines()
            if "DeviceAllow" in line or "Unknown key" in line or "Failed to parse" in line
        ]  # fmt: skip
        assert not problems, problems
