"""Live coverage over a real WebSocket (issue 27): memory agents fly a survey on loopback TCP, the
stream carries a ``coverage`` message per survey mission (seen %, the raster, distance and ETA),
bounded by the hub's period rather than the status reports, and the re-task proposal and the
operator's decision arrive as events while they happen."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gcs.http.client import StatusMessage
from gcs.missions.live_coverage import LiveRaster, distance_progress, unpack_mask
from gcs.missions.retask import SurveyRecord, flown_m
from gcs.missions.runner import AgentProgress, MissionProgress
from gcs.observe.events import Event
from gcs.planning.seen import seen_grid
from protocol.actions import ReturnToLaunch, Waypoints
from protocol.geo import offset_latlon
from protocol.taskfile import SurveyArea
from tests.api.fleet import client, running_fleet, survey_task
from tests.backbone.helpers import HOME


async def test_stream_carries_coverage_and_the_retask_as_it_happens(tmp_path: Path) -> None:
    task = survey_task()
    assert task.survey is not None
    async with running_fleet(tmp_path, drones=2, speedup=3.0) as fleet, client(fleet) as gcs:
        mission_id = await gcs.submit(task)
        coverage: list[dict[str, Any]] = []
        kinds: list[str] = []
        statuses = 0
        applied_at: list[int] = []  # coverage messages received when the re-task was applied
        drone_2 = fleet.daemon.agents.sessions["drone-2"]

        async def consume() -> None:
            nonlocal statuses
            async for message in gcs.stream():
                if isinstance(message, StatusMessage):
                    statuses += 1
                elif isinstance(message, Event):
                    kinds.append(message.kind)
                    if message.kind == "retask_applied":
                        applied_at.append(len(coverage))
                    if message.kind == "retask_proposed":
                        assert message.data and message.data["dropped"] == "drone-2"
                        await gcs.retask(mission_id, "accept", message.data["id"])
                elif message.get("type") == "coverage":
                    assert message["mission_id"] == mission_id
                    coverage.append(message)
                    flying = any(d["state"] == "flying" and d["flown_m"] > 20 for d in message["drones"])
                    surveying = drone_2.status is not None and drone_2.status.step >= 2
                    if message["covered_pct"] > 5 and flying and surveying and "rtl" not in kinds:
                        kinds.append("rtl")
                        await gcs.rtl_all(["drone-2"])  # the operator takes it out of the survey
                    if message["state"] != "running":  # the last one, once the mission ended
                        return

        await asyncio.wait_for(consume(), 120)
        assert kinds.index("retask_proposed") < kinds.index("retask_applied")
        assert len(coverage) < statuses  # the hub's period bounds them, not the status reports
        pcts = [m["covered_pct"] for m in coverage]
        assert pcts == sorted(pcts) and pcts[0] < 100
        final = coverage[-1]
        assert final["state"] == "completed" and final["eta_s"] is None
        assert sum(m["state"] != "running" for m in coverage) == 1
        assert final["covered_pct"] >= 95.0  # drone-1 flew drone-2's unseen share too
        last = coverage[applied_at[0]]  # the first one computed after the re-task was applied
        grid = last["grid"]
        inside = unpack_mask(grid["inside"], grid["rows"], grid["cols"])
        seen = unpack_mask(grid["seen"], grid["rows"], grid["cols"])
        assert not (seen & ~inside).any()
        assert 100.0 * seen.sum() / inside.sum() == pytest.approx(last["covered_pct"], abs=0.01)
        assert last["area_m2"] == pytest.approx(1600.0, rel=0.1)
        assert inside.sum() * grid["cell_m"] ** 2 == pytest.approx(last["area_m2"], rel=0.01)
        sw, ne = offset_latlon(HOME[0], HOME[1], 10, -5), offset_latlon(HOME[0], HOME[1], 50, 35)
        assert grid["sw"] == pytest.approx(list(sw), abs=1e-6)  # the grid ends within a cell past the area
        assert grid["ne"] == pytest.approx(list(ne), abs=4e-5)
        drones = {d["agent"]: d for d in last["drones"]}
        assert drones["drone-2"]["state"] == "left" and drones["drone-2"]["remaining_m"] == 0
        assert drones["drone-1"]["planned_m"] > drones["drone-1"]["flown_m"] > 0
        if last["state"] == "running" and drones["drone-1"]["state"] == "flying":
            assert last["eta_s"] is not None and last["eta_s"] > 0
        assert {d["state"] for d in final["drones"]} == {"done", "left"}


def test_distance_progress_eta_is_the_slowest_drone_at_its_speed() -> None:
    area = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((0, 0), (0, 100), (100, 100), (100, 0))]
    line = [offset_latlon(HOME[0], HOME[1], 0, e) for e in (0, 100)]
    plan = [
        Waypoints(step=0, points=[{"lat": a, "lon": o, "alt": 10} for a, o in line], speed=4.0),
        ReturnToLaunch(step=1),
    ]
    rec = SurveyRecord("m", SurveyArea(area=area, swath_m=10.0), {"a": plan, "b": plan, "c": plan})
    half = offset_latlon(HOME[0], HOME[1], 0, 50)
    rec.tracks = {"a": [(HOME[0], HOME[1], 10.0), (half[0], half[1], 10.0)], "b": [(HOME[0], HOME[1], 10.0)]}
    members = [
        AgentProgress(
            agent=a,
            cid=1,
            connected=True,
            excluded=a == "c",
            step=0,
            completed_step=-1,
            last_step=1,
            waiting_sync=None,
            done=False,
        )
        for a in ("a", "b", "c")
    ]
    progress = MissionProgress(
        id="m", name="m", state="running", result=None, sync_steps=[], released_steps=[], agents=members
    )
    drones, eta = distance_progress(rec, progress, {"a": 10.0, "b": 0.2})
    by = {d.agent: d for d in drones}
    assert by["a"].planned_m == pytest.approx(200.0, rel=0.01)  # out and home
    assert by["a"].remaining_m == pytest.approx(150.0, rel=0.01)
    assert by["c"].state == "left" and by["c"].remaining_m == 0
    assert eta == pytest.approx(200.0 / 4.0, rel=0.01)  # b hovers: its plan's 4 m/s, 200 m to go
    assert unpack_mask("wA==", 1, 3).tolist() == [[True, True, False]]
    assert np.packbits([1, 1, 0]).tobytes() == b"\xc0"


def test_live_raster_swept_in_pieces_equals_the_whole_tracks_at_once() -> None:
    area = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((0, 0), (0, 120), (90, 120), (90, 0))]

    def wavy(n0: float) -> list[tuple[float, float, float]]:  # heights vary: footprints too
        return [
            (*offset_latlon(HOME[0], HOME[1], n0 + 3 * math.sin(k / 5), k * 1.5), 2.0 + k % 9)
            for k in range(80)
        ]

    tracks = {"a": wavy(20.0), "b": wavy(60.0)}
    rec = SurveyRecord("m", SurveyArea(area=area, swath_m=12.0, altitude_m=8.0), {"a": [], "b": []})
    live = LiveRaster.of(rec)
    for end in (1, 2, 17, 18, 50, 80):  # the tracks grow between messages, as the ticks append
        rec.tracks = {a: t[:end] for a, t in tracks.items()}
        live.update(rec)
    whole = seen_grid(area, list(tracks.values()), 12.0, 8.0)
    assert whole.seen.any() and np.array_equal(live.grid.seen, whole.seen)
    assert live.flown == pytest.approx({a: flown_m(t) for a, t in tracks.items()})
