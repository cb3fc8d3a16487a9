"""`gcs demo --ardupilot PATH`: the README's demo flown on real ArduCopter SITL, to a landed finish."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from gcs.commands.demo_mission import DemoOptions, simulator_command
from tests.ardupilot.binary import SKIP_REASON, ardupilot_binary
from tests.support.processes import BIN


def test_demo_simulator_command_for_ardupilot() -> None:
    cmd = simulator_command(DemoOptions(home=(-35.36, 149.16, 584.0), ardupilot="/x/arducopter"))
    assert cmd[-2:] == ["--ardupilot", "/x/arducopter"] and "--seed" not in cmd
    assert "--home=-35.36,149.16,584.0" in cmd  # a negative latitude is not taken for an option
    assert "--seed" in simulator_command(DemoOptions())


@pytest.mark.ardupilot
@pytest.mark.slow
@pytest.mark.skipif(ardupilot_binary() is None, reason=SKIP_REASON)
def test_gcs_demo_on_real_ardupilot(tmp_path: Path) -> None:
    binary = ardupilot_binary()
    assert binary is not None
    result = subprocess.run(
        [
            BIN / "gcs",
            "demo",
            "--ardupilot",
            binary,
            "--speedup",
            "5",
            "--timeout",
            "150",
            "--data-dir",
            tmp_path,
        ],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "starting 3 ArduCopter SITL vehicles" in result.stdout
    assert "result: SUCCESS" in result.stdout
    assert "preflight_fix" in result.stderr or "preflight_waiting" not in result.stderr
    assert "Traceback" not in result.stderr
