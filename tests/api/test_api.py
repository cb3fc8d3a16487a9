"""HTTP/WebSocket API against a daemon with in-process memory agents (real loopback TCP and HTTP)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from gcs.http.client import ApiError, StatusMessage
from gcs.observe.events import Event
from protocol.geo import offset_latlon
from protocol.packets import FenceCircle, Geofence
from tests.api.fleet import client, running_fleet
from tests.backbone.helpers import HOME, survey_mission
from tests.support.polling import wait_for


def area(north: float = 12.0, size: float = 20.0) -> list[tuple[float, float]]:
    return [
        offset_latlon(HOME[0], HOME[1], n, e)
        for n, e in ((north, -4), (north, size), (north + size, size), (north + size, -4))
    ]


async def test_fleet_reads_agents_history_and_openapi(tmp_path: Path) -> None:
    async with running_fleet(tmp_path) as fleet, client(fleet) as gcs:
        agents = await gcs.agents()
        assert [a.identity for a in agents] == ["drone-1", "drone-2", "drone-3"]
        assert all(a.connected and a.status is not None and a.link_age_s is not None for a in agents)
        await asyncio.sleep(0.5)
        history = await gcs.history("drone-2", limit=3)
        assert len(history) == 3 and history[0].received <= history[-1].received
        assert (await gcs.agent("drone-1")).cid == agents[0].cid
        async with fleet.client() as http:
            missing = await http.get("/api/v1/agents/nobody")
            assert missing.status_code == 404
            assert missing.headers["content-type"] == "application/problem+json"
            assert "never connected" in missing.json()["detail"]
            schema = (await http.get("/openapi.json")).json()
            for path in ("/api/v1/plan", "/api/v1/missions/plan", "/api/v1/fleet/rtl", "/api/v1/geofence"):
                assert path in schema["paths"]
            assert "SearchPlanRequest" in schema["components"]["schemas"]
            ui = await http.get("/ui/")
            assert ui.status_code == 200 and "fleetgcs" in ui.text


async def test_mutating_calls_need_the_token(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1) as fleet, fleet.client(token=False) as http:
        for path in ("/api/v1/missions", "/api/v1/fleet/rtl", "/api/v1/fleet/hold", "/api/v1/geofence"):
            response = await http.post(path, json={})
            assert response.status_code == 401, path
            assert response.json()["title"] == "unauthorized"
        wrong = await http.post("/api/v1/fleet/rtl", headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401


async def test_events_filter_by_kind_agent_severity_and_last(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2) as fleet, client(fleet) as gcs:
        fleet.daemon.events.publish("custom_alarm", "hot", severity="error", agent="drone-2")
        joined = await gcs.events(kind="agent_joined")
        assert sorted(e.agent for e in joined) == ["drone-1", "drone-2"]
        assert [e.kind for e in await gcs.events(agent="drone-2", severity="error")] == ["custom_alarm"]
        await wait_for(lambda: fleet.daemon.services, 1, "hub")
        await asyncio.sleep(0.1)
        last = await gcs.events(last=1)
        assert [e.kind for e in last] == ["custom_alarm"]
        assert all(e.id > joined[0].id for e in await gcs.events(since_id=joined[0].id))
        async with fleet.client() as http:
            bad = await http.get("/api/v1/events", params={"limit": 0})
            assert bad.status_code == 422 and bad.headers["content-type"] == "application/problem+json"


async def test_stream_sends_snapshot_status_and_events(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2) as fleet, client(fleet) as gcs:
        seen_status: set[str] = set()
        events: list[Event] = []
        hello = None

        async def consume() -> None:
            nonlocal hello
            async for message in gcs.stream(agents=["drone-1", "drone-2"]):
                if isinstance(message, dict):
                    hello = message
                    fleet.daemon.events.publish("stream_probe", "hello from the test")
                elif isinstance(message, StatusMessage):
                    seen_status.add(message.agent)
                    assert message.status.position.lat == pytest.approx(HOME[0], abs=0.01)
                elif isinstance(message, Event):
                    events.append(message)
                if len(seen_status) == 2 and any(e.kind == "stream_probe" for e in events):
                    return

        await asyncio.wait_for(consume(), 10)
        assert hello is not None and len(hello["agents"]) == 2
        only_one = gcs.statuses(agents=["drone-1"], max_rate_hz=2)
        names = [(await anext(only_one))[0] for _ in range(3)]
        await only_one.aclose()
        assert names == ["drone-1"] * 3


async def test_task_file_mission_completes_and_reports_progress(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=12.0) as fleet, client(fleet) as gcs:
        task = survey_mission(["drone-1", "drone-2"], sync_legs=1)
        mission_id = await gcs.submit(task)
        geometry = (await (await gcs._http.get(f"/api/v1/missions/{mission_id}/plan")).aread()).decode()
        assert "drone-1" in geometry
        progress = await gcs.wait_mission(mission_id, timeout=40)
        assert progress.state == "completed" and all(a.done for a in progress.agents)
        listed = await gcs.missions()
        assert listed[0].id == mission_id and listed[0].state == "completed"
        with pytest.raises(ApiError) as busy:
            await gcs.submit(survey_mission(["drone-9"]))
        assert busy.value.status == 422 and "not connected" in busy.value.detail


async def test_couas_task_file_and_invalid_documents(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1, speedup=12.0) as fleet, client(fleet) as gcs:
        cid = fleet.daemon.agents.sessions["drone-1"].cid
        rows = [
            {"Action_type": 0, "CID": cid, "Step": 0, "Sync": 1, "Alt": 4},
            {"Action_type": 2, "CID": cid, "Step": 1, "N": 6, "E": 0},
            {"Action_type": 3, "CID": cid, "Step": 2},
        ]
        progress = await gcs.run_mission(rows, timeout=40)
        assert progress.state == "completed"
        for document, words in (
            ({"plans": []}, "plans"),
            ([{"Action_type": 1, "CID": cid, "Step": 0}], "lacks"),
            ("nonsense", "invalid task file"),
            ({"plans": [{"agent": "drone-1", "actions": [{"kind": "land", "step": 0}]}]}, "takeoff"),
        ):
            with pytest.raises(ApiError) as bad:
                await gcs.submit(document)  # type: ignore[arg-type]
            assert bad.value.status == 422 and words in str(bad.value), (document, bad.value)


async def test_plan_previews_for_search_psa_and_rsa(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2) as fleet, client(fleet) as gcs:
        search = await gcs.plan({"method": "search", "area": area(), "swath_m": 10, "altitude_m": 6})
        assert [d.agent for d in search.drones] == ["drone-1", "drone-2"]
        assert all(d.length_m > 0 and d.time_s > 0 and d.energy_wh > 0 for d in search.drones)
        assert search.coverage_pct is not None and search.coverage_pct > 90
        assert search.taskfile.plans[0].actions[0].kind == "takeoff"
        targets = [{"lat": a, "lon": b} for a, b in area(30, 40)]
        psa = await gcs.plan(
            {"method": "psa", "targets": targets, "link_range_m": 20, "drones": ["drone-1", "drone-2"]}
        )
        assert len(psa.drones) == 2 and psa.targets is not None
        rsa = await gcs.plan(
            {
                "method": "rsa",
                "origin": {"lat": HOME[0], "lon": HOME[1]},
                "cell_size_m": 5,
                "rows": [[1, 1, 1, 1], [1, 0, 0, 1], [1, 0, 0, 1], [1, 1, 1, 1]],
                "flight_distance_m": 500,
            }
        )
        assert rsa.summary["drones_needed"] >= 1
        bowtie = [area()[i] for i in (0, 2, 1, 3)]
        for request, words in (
            ({"method": "search", "area": bowtie}, "cannot plan"),
            ({"method": "search"}, "exactly one"),
            ({"method": "search", "area": area(size=20000), "swath_m": 1}, "limit"),
            ({"method": "teleport"}, "invalid request"),
            (
                {"method": "rsa", "origin": {"lat": 0, "lon": 0}, "cell_size_m": 5, "rows": [[1, 1]]},
                "no missed",
            ),
        ):
            with pytest.raises(ApiError) as bad:
                await gcs.plan(request)
            assert bad.value.status == 422 and (words in bad.value.detail or words in bad.value.title), (
                bad.value
            )
        # A bow-tie is located in lat/lon (it read "(0.00, 0.00)" in the planner's local metres) and
        # comes back with its outline and crossing, for the dashboard to draw.
        answer = await gcs._http.post("/api/v1/plan", json={"method": "search", "area": bowtie})
        body = answer.json()
        assert answer.status_code == 422 and "(0.00, 0.00)" not in body["detail"], body
        crossing = offset_latlon(HOME[0], HOME[1], 22.0, 8.0)
        assert f"at ({crossing[0]:.6f}, {crossing[1]:.6f})" in body["detail"], body["detail"]
        assert body["area"] == [list(p) for p in bowtie]
        assert body["crossings"] == [pytest.approx(list(crossing), abs=1e-7)]


async def test_plan_and_fly_then_pause_resume_and_abort_hold(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=3.0) as fleet, client(fleet) as gcs:
        created = await gcs.submit_plan(
            {"method": "search", "area": area(20, 30), "swath_m": 10, "altitude_m": 5}
        )
        assert created.plan is not None
        mission_id = created.mission_id
        geometry = (await gcs._http.get(f"/api/v1/missions/{mission_id}/plan")).json()
        assert geometry["area"] and geometry["swath_m"] == 10
        await gcs.pause(mission_id)
        sessions = [fleet.daemon.agents.sessions[n] for n in ("drone-1", "drone-2")]
        await wait_for(lambda: all(s.status and s.status.paused for s in sessions), 5, "pause")
        await gcs.resume(mission_id)
        await wait_for(lambda: all(s.status and not s.status.paused for s in sessions), 5, "resume")
        await wait_for(lambda: all(s.status and s.status.step >= 1 for s in sessions), 20, "flying")
        coverage = (await gcs._http.get(f"/api/v1/missions/{mission_id}/coverage")).json()
        assert coverage["swath_m"] == 10 and coverage["samples"] > 0
        progress = await gcs.abort(mission_id, then="hold")
        assert progress.state == "aborted"
        await wait_for(lambda: all(s.status and s.status.paused for s in sessions), 5, "hold after abort")
        with pytest.raises(ApiError) as again:
            await gcs.pause(mission_id)
        assert again.value.status == 409
        with pytest.raises(ApiError) as missing:
            await gcs.abort("m-nope")
        assert missing.value.status == 404


async def test_fleet_commands_geofence_and_metrics(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=12.0) as fleet, client(fleet) as gcs:
        mission_id = await gcs.submit(survey_mission(["drone-1", "drone-2"], sync_legs=3))
        sessions = [fleet.daemon.agents.sessions[n] for n in ("drone-1", "drone-2")]
        await wait_for(
            lambda: all(s.status and s.status.position.alt_rel > 2 for s in sessions), 15, "airborne"
        )
        held = await gcs.hold_all()
        assert sorted(held.delivered) == ["drone-1", "drone-2"]
        await wait_for(lambda: all(s.status and s.status.paused for s in sessions), 5, "hold")
        assert (await gcs.resume_all()).command == "resume"
        result = await gcs.rtl_all(["drone-1", "drone-2"])
        assert result.aborted_missions == [mission_id] and sorted(result.delivered) == ["drone-1", "drone-2"]
        await wait_for(  # each drone flies its deconflicted return program
            lambda: all(s.status and (s.status.mission_id or "").startswith("return-rtl") for s in sessions),
            10,
            "rtl",
        )
        landed = await gcs.land_all()
        assert landed.command == "land"
        fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=300), breach_action="report")
        assert sorted(await gcs.set_geofence(fence)) == ["drone-1", "drone-2"]
        assert await gcs.geofence() == fence
        async with fleet.client() as http:
            text = (await http.get("/metrics")).text
        for name in (
            "fleetgcs_agents_connected 2.0",
            'fleetgcs_status_reports_total{agent="drone-1"}',
            "fleetgcs_status_rate_hz",
            "fleetgcs_barrier_wait_seconds_count",
            'fleetgcs_command_latency_seconds_count{command="rtl"}',
            'fleetgcs_holds_total{agent="drone-1"}',
            "fleetgcs_agents_held",
        ):
            assert name in text, name
        rate = float(
            next(line.split()[1] for line in text.splitlines() if line.startswith("fleetgcs_status_rate_hz"))
        )
        assert rate > 5  # two agents at 10 Hz
