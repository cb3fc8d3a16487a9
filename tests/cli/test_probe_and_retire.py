"""`agent doctor` probes without joining the fleet; an operator retires an agent (API and CLI)."""

from __future__ import annotations

import asyncio
from pathlib import Path

from agent.autopilot.memory import MemoryAutopilot
from agent.config import AgentConfig
from agent.doctor import Report, check_autopilot, diagnose
from tests.api.fleet import running_fleet
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.cli.common import gcs
from tests.support.polling import wait_for


async def test_doctor_probe_is_authenticated_but_never_a_fleet_member(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, max_agents=1) as daemon:
        drone = start_agent("drone-1", daemon.listen_port, key)
        try:
            await wait_for(lambda: daemon.agents.session("drone-1") is not None, 10, "drone-1 to join")
            session = daemon.agents.session("drone-1")
            # the probe's own identity, and the running agent's identity, with the fleet full (max 1)
            for identity in ("doctor-probe", "drone-1"):
                config = AgentConfig(identity=identity, gcs_port=daemon.listen_port, key_hex=key)
                report = await diagnose(config, None, drift_interval_s=0, timeout=5)
                text = report.render()
                assert report.ok, text
                assert f"accepted {identity} (probe: not a fleet member)" in text, text
            assert set(daemon.agents.sessions) == {"drone-1"}
            assert daemon.agents.session("drone-1") is session and session is not None and session.open
            assert set(daemon.store.known_agents()) == {"drone-1"}
            kinds = [e.kind for e in daemon.events.history(0, None, None, 1000)]
            assert kinds.count("agent_probe") == 2 and "agent_replaced" not in kinds
            assert kinds.count("agent_joined") == 1
            wrong = AgentConfig(identity="doctor-probe", gcs_port=daemon.listen_port, key_hex=new_key())
            bad = await diagnose(wrong, None, drift_interval_s=0, timeout=5)
            assert not bad.ok and "wrong key" in bad.render()
        finally:
            await stop_agents([drone])


async def test_retire_an_agent_over_the_api_and_the_command_line(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2, lost_agent_policy="continue") as fleet:
        api = ["--api", fleet.base_url, "--token", "test-token"]
        code, _, err = await gcs("agents", "retire", "drone-1", *api)
        assert (
            code == 2
            and err.strip() == "gcs agents: agent connected: drone-1 is connected: stop its agent first"
        )
        async with fleet.client() as http:
            created = await http.post(
                "/api/v1/missions", json=survey_mission(["drone-2"]).model_dump(mode="json")
            )
            assert created.status_code == 201, created.text
            mission_id = created.json()["mission_id"]
            cid = fleet.daemon.agents.sessions["drone-1"].cid
            await fleet.agents[0].kill()
            await fleet.agents[1].kill()
            await wait_for(lambda: not fleet.daemon.agents.connected(), 10, "both agents to go")
            busy = await http.delete("/api/v1/agents/drone-2")
            assert busy.status_code == 409 and mission_id in busy.json()["detail"], busy.text
            assert (
                await http.delete("/api/v1/agents/drone-1", headers={"Authorization": "x"})
            ).status_code == 401

            code, out, err = await gcs("agents", "retire", "drone-1", *api)
            assert code == 0, err
            assert f"drone-1 (cid {cid}) retired" in out
            listed = [a["identity"] for a in (await http.get("/api/v1/agents")).json()]
            assert listed == ["drone-2"]
            code, out, _ = await gcs("agents", *api)
            assert "drone-1" not in out and "drone-2" in out
            again = await http.delete("/api/v1/agents/drone-1")
            assert again.status_code == 404
            assert [e.kind for e in fleet.daemon.events.history(0, "agent_retired", None, 10)] == [
                "agent_retired"
            ]

            back = start_agent("drone-1", fleet.daemon.listen_port, fleet.key)  # the CID stayed reserved
            try:
                await wait_for(lambda: fleet.daemon.agents.session("drone-1") is not None, 10, "drone-1 back")
                assert fleet.daemon.agents.sessions["drone-1"].cid == cid
            finally:
                await stop_agents([back])


class _LateFixAutopilot(MemoryAutopilot):
    """The memory vehicle as a MAVLink link looks at its first heartbeat: no GPS report yet.

    Its fix (10 satellites) arrives 0.5 s later, as GPS_RAW_INT does after the link comes up.
    """

    async def connect(self, timeout: float = 30.0) -> None:
        await super().connect(timeout)
        fix = self.telemetry().gps_fix, self.telemetry().satellites
        self._t.gps_fix, self._t.satellites = 0, 0
        loop = asyncio.get_running_loop()
        loop.call_later(0.5, lambda: setattr(self._t, "gps_fix", fix[0]))
        loop.call_later(0.5, lambda: setattr(self._t, "satellites", 10))


async def test_doctor_waits_for_the_first_gps_report() -> None:
    """`agent doctor` read the GPS right after the first heartbeat and said "fix 0 (0 satellites)"."""
    report = Report()
    await check_autopilot(report, _LateFixAutopilot(), timeout=5.0)
    gps = next(c for c in report.checks if c.name == "GPS")
    assert gps.verdict == "ok" and gps.detail == "fix 3, 10 satellites", gps
