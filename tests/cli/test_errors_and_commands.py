"""Each operator error of the command-line tools is one line, not a traceback; fleet and mission
control from the shell (`gcs fleet`, `gcs mission`); `--version` everywhere."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from gcs.observe.telemetry import to_csv, to_geojson
from tests.api.fleet import running_fleet
from tests.backbone.helpers import survey_mission
from tests.cli.common import gcs, interrupt_after, one_line, run_tool
from tests.support.paths import ROOT
from tests.support.polling import wait_for
from tests.support.processes import BIN

DOWN = "http://127.0.0.1:9"  # discard port: nothing listens


def run(*argv: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("tool", ["gcs", "agent", "sitl"])
def test_version(tool: str) -> None:
    result = run(BIN / tool, "--version")
    assert result.returncode == 0 and result.stdout.startswith(f"{tool} 0."), result


def test_plan_on_a_missing_file_a_directory_and_a_self_intersecting_area(tmp_path: Path) -> None:
    missing = run(BIN / "gcs", "plan", tmp_path / "nope.geojson", "--swath", "10")
    assert missing.returncode == 2
    assert (
        one_line(missing.stderr)
        == f"gcs plan: cannot use {tmp_path / 'nope.geojson'}: No such file or directory"
    )
    directory = run(BIN / "gcs", "plan", tmp_path, "--swath", "10")
    assert directory.returncode == 2 and one_line(directory.stderr).endswith(": Is a directory")

    bowtie = tmp_path / "bowtie.json"  # corners 2 and 3 swapped: edges 1-2 and 3-4 cross
    bowtie.write_text(
        json.dumps([[47.3970, 8.5450], [47.3980, 8.5460], [47.3980, 8.5450], [47.3970, 8.5460]])
    )
    crossed = run(BIN / "gcs", "plan", bowtie, "--swath", "10", "--out", tmp_path / "out")
    line = one_line(crossed.stderr)
    assert crossed.returncode == 2 and "self-intersecting area (lat, lon)" in line, line
    assert "vertex 1 (47.397000, 8.545000) -> vertex 2 (47.398000, 8.546000)" in line, line
    assert "at (47.397500, 8.545500)" in line, line


def test_commands_with_the_daemon_down() -> None:
    for argv in (
        ["agents"],
        ["fleet", "rtl", "--token", "t"],
        ["mission", "pause", "m-1", "--token", "t"],
        ["mission", "list"],
    ):
        result = run(BIN / "gcs", *argv, "--api", DOWN)
        assert result.returncode == 3, result
        assert "cannot reach the daemon at http://127.0.0.1:9" in one_line(result.stderr)
        assert "is `gcs serve` running?" in result.stderr


def test_commands_without_a_token_file(tmp_path: Path) -> None:
    result = run(BIN / "gcs", "fleet", "hold", "--api", DOWN, "--data-dir", tmp_path)
    assert result.returncode == 2 and "no API token: cannot read" in one_line(result.stderr)


def test_serve_with_a_port_in_use(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for listen, http, which in (
            ("127.0.0.1:0", f"127.0.0.1:{port}", "HTTP API"),
            (f"127.0.0.1:{port}", "127.0.0.1:0", "agent listener"),
        ):
            result = run(BIN / "gcs", "serve", "--listen", listen, "--http", http, "--data-dir", tmp_path)
            line = one_line(result.stderr)
            assert result.returncode == 2 and f"{which} 127.0.0.1:{port}: address already in use" in line


def test_exports_carry_the_gps_fix() -> None:
    base = dict(
        alt_rel=0.0, alt_amsl=488.0, vn=0.0, ve=0.0, vd=0.0, heading_deg=0.0, battery_pct=90.0,
        voltage_v=16.0, current_a=1.0, mode="GUIDED", landed=0, step=-1, mission_id=None,
    )  # fmt: skip
    samples = [
        {**base, "time": 1.0, "gps_fix": 0, "satellites": 0, "lat": None, "lon": None, "armed": 1},
        {**base, "time": 2.0, "gps_fix": 3, "satellites": 9, "lat": 47.1, "lon": 8.1, "armed": 1},
        {**base, "time": 3.0, "gps_fix": 6, "satellites": 14, "lat": 47.2, "lon": 8.2, "armed": 0},
    ]
    rows = to_csv(samples).splitlines()
    assert rows[0].startswith("time,gps_fix,satellites,lat,lon,")
    assert rows[1].startswith("1.0,0,0,,,") and rows[3].startswith("3.0,6,14,47.2,8.2,")
    (feature,) = to_geojson("d", [samples])["features"]
    assert feature["geometry"]["coordinates"] == [[8.1, 47.1, 0.0], [8.2, 47.2, 0.0]]
    assert feature["properties"]["gps_fix"] == [3, 6] and feature["properties"]["samples_without_3d_fix"] == 1


async def test_fleet_and_mission_control_from_the_shell(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=1.0) as fleet:  # the mission lasts > 20 s
        api = ["--api", fleet.base_url, "--token", "test-token"]
        one, two = (fleet.daemon.agents.session(f"drone-{i}") for i in (1, 2))
        assert one is not None and two is not None

        code, _, err = await gcs("mission", "pause", *api)
        assert code == 1 and one_line(err) == "gcs mission: no mission is running"
        code, out, err = await gcs("fleet", "hold", "--drone", "drone-1", *api)
        assert code == 0 and out.strip() == "hold sent to drone-1", err
        await wait_for(lambda: one.status is not None and one.status.paused, 10, "drone-1 to hold")
        assert two.status is not None and not two.status.paused
        code, out, _ = await gcs("fleet", "resume", *api)
        assert code == 0 and "resume sent to drone-1, drone-2" in out
        await wait_for(lambda: one.status is not None and not one.status.paused, 10, "drone-1 to resume")
        code, _, err = await gcs("fleet", "land", "--drone", "ghost", *api)
        assert code == 1 and one_line(err) == "gcs fleet: land reached no drone: none of ghost is connected"

        async with fleet.client() as http:
            # long enough (legs to 90 m north) to outlast four CLI processes on a loaded machine
            task = survey_mission(["drone-1", "drone-2"], sync_legs=9).model_dump(mode="json")
            created = await http.post("/api/v1/missions", json=task)
            mission_id = created.json()["mission_id"]
        code, out, err = await gcs("mission", "pause", *api)
        assert code == 0 and out.startswith(f"mission {mission_id}: running"), err
        code, out, _ = await gcs("mission", "list", *api)
        assert mission_id in out and "running" in out
        code, out, err = await gcs("mission", "resume", mission_id, *api)
        assert code == 0, err
        code, out, err = await gcs("mission", "abort", "--then", "hold", *api)
        assert code == 0 and out.startswith(f"mission {mission_id}: aborted"), out + err
        code, _, err = await gcs("mission", "pause", mission_id, *api)
        assert code == 2 and one_line(err).startswith("gcs mission: mission not running:")
        code, _, err = await gcs("mission", "abort", "no-such-mission", *api)
        assert code == 2 and one_line(err).startswith("gcs mission: no such mission:")
        code, _, err = await gcs("fleet", "rtl", "--api", fleet.base_url, "--token", "wrong")
        assert code == 2 and one_line(err).startswith("gcs fleet: unauthorized:")


async def test_ctrl_c_in_gcs_run_and_the_examples(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1, speedup=1.0) as fleet:
        api = ["--api", fleet.base_url, "--token", "test-token"]
        area = ["--area", "47.3979,8.5454", "47.3979,8.5461", "47.3983,8.5461"]
        fly = [sys.executable, ROOT / "examples" / "fly_search.py", "--api", fleet.base_url, *area]
        code, out, err = await run_tool(*fly, "--token", "wrong")
        assert code == 2 and one_line(err).startswith("fly_search: HTTP 401 unauthorized"), out + err

        task_file = tmp_path / "mission.json"
        task_file.write_text(survey_mission(["drone-1"], sync_legs=3).model_dump_json())
        code, out, err = await interrupt_after([BIN / "gcs", "run", task_file, *api], "started")
        assert code == 130, out + err
        assert "keeps flying on the daemon" in one_line(err) and "gcs mission pause|abort" in err
        (mission_id,) = fleet.daemon.missions.active  # still running: Ctrl-C only stopped following

        example = [sys.executable, ROOT / "examples" / "watch_fleet.py", "--api", fleet.base_url]
        code, out, err = await interrupt_after(example, "drone-1")
        assert code == 130 and one_line(err) == "watch_fleet: interrupted", out + err

        assert mission_id in fleet.daemon.missions.active


def test_agent_with_a_serial_device_that_is_not_there(tmp_path: Path) -> None:
    key = tmp_path / "key"
    key.write_text("ab" * 32)
    device = "/dev/ttyACM97"  # not there
    common = ["--id", "pi-9", "--key-file", key, "--autopilot", f"{device}:115200", "--gcs", "127.0.0.1:9"]
    agent = run(BIN / "agent", "run", *common)
    line = one_line(agent.stderr)
    assert agent.returncode == 1 and line.startswith(f"agent run: cannot open '{device}:115200'"), line
    assert "no such device: is the flight controller connected?" in line
    doctor = run(BIN / "agent", "doctor", *common, "--drift-interval", "0", "--timeout", "3")
    assert doctor.returncode == 1 and "[FAIL] autopilot link" in doctor.stdout
    assert "-> no such device" in doctor.stdout and "check the wiring" not in doctor.stdout, doctor.stdout
