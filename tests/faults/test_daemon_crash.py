"""`kill -9` of the daemon process mid-mission, then a restart on the same data directory.

Real processes: `gcs serve` and two `agent run --autopilot-backend memory` agents. The agents keep
flying through the outage; the restarted daemon restores the mission from SQLite, the agents
reconnect, and the mission completes. Nothing accepted before the kill may be lost: the mission,
the released sync steps, each agent's completed step, and every event.
"""

from __future__ import annotations

import sqlite3
import subprocess
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.backbone.helpers import HOME, survey_mission
from tests.support.processes import agent_process, serve_daemon, stop_processes, wait_ready

NAMES = ["crash-1", "crash-2"]
SYNC_STEPS = [0, 1, 2, 3, 4, 5]


def _agent(name: str, index: int, port: int, key_file: Path) -> subprocess.Popen[bytes]:
    return agent_process(name, port, key_file, (HOME[0], HOME[1] + index * 0.0001, HOME[2]), speedup=4)


def _poll(what: str, timeout: float, probe: Any) -> Any:
    """Call ``probe`` until it returns something truthy (bounded); HTTP errors count as 'not yet'."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = probe()
        except httpx.HTTPError:
            value = None
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.mark.slow
def test_kill_9_mid_mission_then_restart_loses_nothing(tmp_path: Path) -> None:
    data_dir = tmp_path / "gcs"
    ready = tmp_path / "ready"
    procs: list[subprocess.Popen[bytes]] = []
    serve = serve_daemon(data_dir, ready, "127.0.0.1:0")
    procs.append(serve)
    try:
        agent_port, http_port = wait_ready(ready, serve)
        procs += [_agent(n, i, agent_port, data_dir / "fleet.key") for i, n in enumerate(NAMES)]
        api = httpx.Client(base_url=f"http://127.0.0.1:{http_port}", timeout=5.0)
        _poll(
            "two agents",
            20,
            lambda: sum(a["connected"] for a in api.get("/api/v1/agents").json()) == 2,
        )
        token = (data_dir / "api.token").read_text().strip()
        task = survey_mission(NAMES, sync_legs=5, sync_timeout_s=60)
        created = api.post(
            "/api/v1/missions",
            content=task.model_dump_json(),
            headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
        )
        assert created.status_code == 201, created.text
        mission_id = created.json()["mission_id"]

        def progress(client: httpx.Client) -> dict[str, Any]:
            return client.get(f"/api/v1/missions/{mission_id}").json()

        before = _poll(
            "steps 0 and 1 released", 30, lambda: (p := progress(api))["released_steps"][:2] == [0, 1] and p
        )
        assert before["state"] == "running", before
        events_before = api.get("/api/v1/events", params={"limit": 5000}).json()
        api.close()

        serve.kill()  # SIGKILL: no shutdown code runs
        serve.wait(timeout=10)
        assert serve.returncode == -9
        completed_before = {a["agent"]: a["completed_step"] for a in before["agents"]}

        restarted = serve_daemon(data_dir, ready, f"127.0.0.1:{agent_port}")
        procs.append(restarted)
        _, http_port = wait_ready(ready, restarted)
        api = httpx.Client(base_url=f"http://127.0.0.1:{http_port}", timeout=5.0)
        after = _poll("mission end", 60, lambda: (p := progress(api))["state"] != "running" and p)
        assert after["state"] == "completed", after
        assert after["released_steps"] == SYNC_STEPS
        for row in after["agents"]:
            assert row["done"] and row["completed_step"] >= completed_before[row["agent"]]

        events_after = api.get("/api/v1/events", params={"limit": 5000}).json()
        api.close()
        by_id = {e["id"]: e for e in events_after}
        for event in events_before:  # every event from before the kill is still there, unchanged
            assert by_id.get(event["id"]) == event, event
        kinds = [e["kind"] for e in events_after]
        assert "mission_restored" in kinds and "mission_completed" in kinds
        assert "mission_resent" not in kinds  # the agents kept their queues; nothing re-flown
        released = [e["data"]["step"] for e in events_after if e["kind"] == "sync_released"]
        assert released == SYNC_STEPS  # each step released exactly once across both daemon lives
        assert [e["agent"] for e in events_after if e["kind"] == "agent_joined"].count(NAMES[0]) >= 2
    finally:
        stop_processes(procs)

    with sqlite3.connect(f"file:{data_dir / 'fleetgcs.sqlite'}?mode=ro", uri=True) as db:
        state = db.execute("SELECT state FROM missions WHERE id=?", (mission_id,)).fetchone()
        assert state == ("completed",)
        steps = [
            r[0]
            for r in db.execute("SELECT step FROM releases WHERE mission_id=? ORDER BY step", (mission_id,))
        ]
        assert steps == SYNC_STEPS
        progress_rows = dict(
            db.execute("SELECT agent, completed_step FROM mission_agents WHERE mission_id=?", (mission_id,))
        )
        assert progress_rows == {name: SYNC_STEPS[-1] + 1 for name in NAMES}
        stored_ids = {r[0] for r in db.execute("SELECT id FROM events")}
        assert {e["id"] for e in events_before} <= stored_ids
