"""The command-line tools as separate processes: `gcs serve`, `agent run`, `gcs run`, `gcs agents`."""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import time
from pathlib import Path

import pytest

from tests.backbone.helpers import survey_mission
from tests.support.processes import BIN, agent_process, serve_daemon, wait_ready


@pytest.mark.slow
def test_serve_agents_and_run_a_mission_from_the_command_line(tmp_path: Path) -> None:
    data_dir = tmp_path / "gcs"
    ready = tmp_path / "ready"
    serve = serve_daemon(data_dir, ready, options=("--status-period", "0.1"), stderr=subprocess.PIPE)
    agents: list[subprocess.Popen[bytes]] = []
    try:
        agent_port, http_port = wait_ready(ready, serve)
        key_file = data_dir / "fleet.key"
        assert oct(key_file.stat().st_mode & 0o777) == "0o600"
        for index, name in enumerate(["cli-1", "cli-2"]):
            lat, lon = 47.397742, 8.545594 + index * 0.0001
            agents.append(agent_process(name, agent_port, key_file, (lat, lon, 488), speedup=8))
        api = ["--api", f"http://127.0.0.1:{http_port}", "--data-dir", str(data_dir)]
        deadline = time.monotonic() + 20
        listing = ""
        while time.monotonic() < deadline:
            listing = subprocess.run([BIN / "gcs", "agents", *api], capture_output=True, text=True).stdout
            if listing.count(" up ") == 2:
                break
            time.sleep(0.2)
        assert "cli-1" in listing and "cli-2" in listing, listing

        task_file = tmp_path / "mission.json"
        task_file.write_text(survey_mission(["cli-1", "cli-2"], sync_legs=2).model_dump_json())
        result = subprocess.run(
            [BIN / "gcs", "run", task_file, "--timeout", "90", *api],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert result.returncode == 0, result.stdout + result.stderr
        assert "completed" in result.stdout and "sync 3/3" in result.stdout

        bad = tmp_path / "bad.json"
        bad.write_text(
            json.dumps([{"Action_type": 1, "CID": 1, "Step": 0, "Sync": 0, "Lat": 1, "Lon": 1, "Alt": 5}])
        )
        rejected = subprocess.run([BIN / "gcs", "run", bad, *api], capture_output=True, text=True, timeout=30)
        assert rejected.returncode == 2 and "first action must be a takeoff" in rejected.stderr

        wrong_token = subprocess.run(
            [BIN / "gcs", "run", task_file, "--token", secrets.token_hex(8), *api],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert wrong_token.returncode == 2 and "unauthorized" in wrong_token.stderr
    finally:
        # SIGTERM the daemon while the agents are still connected: a clean stop, no tracebacks.
        for proc in [serve, *agents]:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
    log = serve.stderr.read().decode(errors="replace") if serve.stderr else ""
    assert serve.returncode == 0, log
    assert "Traceback" not in log and "Exception in callback" not in log, log
    assert os.path.exists(data_dir / "fleetgcs.sqlite")
