"""Closed-loop coverage on daemon + agents + our simulator (issue 27): a dropped drone's share.

A 4-drone region survey planned by ``gcs plan``; drone-2's battery failsafe fires ~40 % into its
share (the simulator's battery set below the agent's low-battery threshold: its own RTL). The
coverage is computed by the test itself from the simulator's sampled ground truth, with the same
eq. 5 footprint (seen_grid):

* policy automatic: the daemon re-tasks the unseen part of drone-2's share to the others at
  once; the area ends >= 99 % seen, within their energy, every drone landed;
* policy ask, the operator rejects over the HTTP API: the gap stays unseen, and the coverage
  report (GET /missions/{id}/report) names it;
* a lost link instead of the failsafe (drone-2's link to the daemon cut, its agent returns home
  on its own, ``lost_agent_policy: continue``): the same automatic re-task closes the gap;
* a pilot takeover instead (a pilot's ground station on drone-2's second MAVLink link selects
  LOITER, tests/support/pilot.py, then lands it where it is): the daemon excludes it and re-tasks
  its share the same way.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from shapely.geometry import LineString, Point

from agent.config import AgentSettings
from gcs.cli import main as gcs_main
from gcs.http.client import FleetClient
from gcs.missions.plan_edit import survey_points
from gcs.planning.geodesy import LocalFrame
from gcs.planning.seen import seen_grid
from protocol.geo import offset_latlon
from protocol.taskfile import TaskFile, load_task_text
from tests.cli.common import gcs
from tests.cooperation.rig import HOME, Rig, rig, wait_for
from tests.faults.proxy import FaultProxy
from tests.support.pilot import PilotStation

pytestmark = pytest.mark.slow

SWATH, ALT = 10.0, 8.0
DROPPED = "drone-2"


def _plan(tmp_path: Path, policy: str) -> TaskFile:
    """A 120 x 60 m field north of home, 4 drones, region division; ``survey.retask`` = policy."""
    corners = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((15, -30), (15, 90), (75, 90), (75, -30))]
    (tmp_path / "area.json").write_text(json.dumps([list(c) for c in corners]))
    out = tmp_path / "plan"
    args = ["plan", str(tmp_path / "area.json"), "--drones", "4", "--division", "region"]
    args += ["--swath", str(SWATH), "--alt", str(ALT), "--home", f"{HOME[0]},{HOME[1]}"]
    args += ["--stagger", "3", "--out", str(out)]
    assert gcs_main(args) == 0
    task = load_task_text((out / "mission.json").read_text())
    assert task.survey is not None
    return task.model_copy(update={"survey": task.survey.model_copy(update={"retask": policy})})


def _share_progress(r: Rig, task: TaskFile) -> float:
    """How far along its share (0..1, by length) drone-2 flies now (simulator ground truth)."""
    plan = next(p for p in task.plans if p.agent == DROPPED)
    frame = LocalFrame(HOME[0], HOME[1])
    share = LineString([frame.local_point(a, b) for a, b in survey_points(plan.actions)])
    s = r.fleet.vehicles[1].state
    return float(share.project(Point(frame.local_point(s.lat, s.lon))) / share.length)


async def _fly_until_drop(
    r: Rig, task: TaskFile, cut: FaultProxy | None = None, drop: Callable[[], Awaitable[None]] | None = None
) -> str:
    """Fly ``task`` until drone-2 is 40 % into its share, then its battery failsafe (or its link
    to the daemon cut through ``cut``, or ``drop``); returns once the daemon excluded it."""
    mission_id = await r.daemon.missions.submit(task)
    survey_step = max(a.step for p in task.plans for a in p.actions if a.kind == "waypoints")
    await wait_for(lambda: r.agents[DROPPED].queue.current_step == survey_step, 60, "drone-2 on its share")
    await wait_for(lambda: _share_progress(r, task) >= 0.4, 60, "drone-2 40 % into its share")
    if drop is not None:
        await drop()
    elif cut is None:
        r.fleet.vehicles[1].set_battery(20.0)  # below the agent's battery_low_pct: its own RTL
    else:
        cut.partition(600.0, "blackhole")
    await wait_for(lambda: r.events("agent_excluded", DROPPED), 20, "drone-2 excluded")
    return mission_id


def _down(r: Rig) -> list[str]:
    """The vehicles still armed or in the air, by the simulator (a cut link reports nothing)."""
    return [n for n, v in zip(r.names, r.fleet.vehicles, strict=True) if not v.state.landed or v.state.armed]


async def _all_landed(r: Rig) -> None:
    try:
        await wait_for(lambda: not _down(r), 90, "every drone landed")
    except AssertionError:
        flying = {n: (s.mode, s.completed_step, s.failsafe) if (s := r.status(n)) else None for n in _down(r)}
        tail = [(e.kind, e.agent, e.message[:90]) for e in r.daemon.events.history(limit=500)[-25:]]
        raise AssertionError(f"not landed: {flying}; last events: {tail}") from None


def _coverage(r: Rig, task: TaskFile) -> float:
    """Seen share of the area from the simulator's samples (the test's own, not the daemon's)."""
    assert task.survey is not None
    tracks = [
        [
            (*offset_latlon(HOME[0], HOME[1], row[k][0], row[k][1]), row[k][2] - HOME[2])
            for row in r.truth
            if row[k][3]
        ]
        for k in range(4)
    ]
    return seen_grid(task.survey.area, tracks, SWATH, ALT).covered_pct


async def _retasked_to_the_end(r: Rig, mission_id: str, task: TaskFile) -> tuple[dict[str, Any], float]:
    """Wait for the re-task, the survey's completion and every landing: the applied re-task's data and
    the coverage by the test's own raster."""
    await wait_for(lambda: r.events("retask_applied"), 30, "the re-task applied")
    await wait_for(lambda: mission_id not in r.daemon.missions.active, 150, "survey end")
    await _all_landed(r)
    progress = r.daemon.missions.progress(mission_id)
    assert progress is not None and progress.state == "completed", progress
    return r.events("retask_applied")[0].data, _coverage(r, task)


async def test_automatic_retask_closes_the_gap_of_a_battery_failsafe(tmp_path: Path) -> None:
    task = _plan(tmp_path, "automatic")
    async with rig(tmp_path, 4) as r:
        mission_id = await _fly_until_drop(r, task)
        applied, covered = await _retasked_to_the_end(r, mission_id, task)
    assert applied["dropped"] == DROPPED and applied["legs"], applied
    assert all(g["energy_wh"] <= g["margin_wh"] for g in applied["legs"])
    assert DROPPED not in {g["ident"] for g in applied["legs"]}
    assert covered >= 99.0, covered


async def test_ask_then_reject_leaves_the_gap_and_the_report_names_it(tmp_path: Path) -> None:
    task = _plan(tmp_path, "ask")
    async with rig(tmp_path, 4, http_host="127.0.0.1", http_port=0, api_token="t") as r:
        mission_id = await _fly_until_drop(r, task)
        await wait_for(lambda: r.events("retask_proposed"), 30, "the proposal")
        api = ["--api", f"http://127.0.0.1:{r.daemon.http_port}", "--token", "t"]
        async with FleetClient(f"http://127.0.0.1:{r.daemon.http_port}", token="t") as client:
            (pending,) = await client.retask_proposals(mission_id)
            assert pending["state"] == "pending" and pending["legs"], pending
            assert all(g["time_s"] > 0 and g["energy_wh"] > 0 for g in pending["legs"])
            code, out, err = await gcs("mission", "retask", mission_id, *api)  # what the operator reads
            assert code == 0 and "r1 pending  drone-2" in out and " Wh" in out, out + err
            code, out, err = await gcs("mission", "retask", mission_id, "reject", *api)
            assert code == 0 and "r1 rejected" in out, out + err
            await wait_for(lambda: mission_id not in r.daemon.missions.active, 150, "survey end")
            await _all_landed(r)
            report = await client.report(mission_id)
            code, text, err = await gcs("mission", "report", mission_id, *api)
        assert code == 0 and "gap r1:" in text and "proposal rejected by the operator" in text, text + err
        covered = _coverage(r, task)
    assert covered < 97.0, covered  # the rejected share stays unseen
    assert report.state == "completed" and report.covered_pct < 97.0
    (gap,) = report.gaps
    assert gap.dropped == DROPPED and gap.state == "rejected" and gap.gap_m2 > 100
    assert gap.gap["coordinates"] and report.missed["coordinates"]
    drones = {d.agent: d for d in report.drones}
    assert "failsafe" in (drones[DROPPED].left or "")
    assert all(d.flown_m > 0 and d.planned_m > 0 for d in drones.values())


async def test_a_lost_link_is_re_tasked_the_same_way(tmp_path: Path) -> None:
    task = _plan(tmp_path, "automatic").model_copy(update={"lost_agent_policy": "continue"})
    proxies: dict[str, FaultProxy] = {}

    async def interpose(name: str, port: int, endpoint: str) -> tuple[int, str]:
        proxies[name] = proxy = await FaultProxy(port, max_stall_s=600.0).start()
        return proxy.port, endpoint

    # The agents return home after 1.5 s (wall) without a word from the daemon, which says
    # something every 0.2 s (keepalives): 12 s of vehicle time at the rig's 8x.
    settings = AgentSettings(status_period_s=0.05, lost_link_action="rtl", lost_link_timeout_s=1.5)
    try:
        async with rig(tmp_path, 4, settings=settings, interpose=interpose, keepalive_s=0.2) as r:
            mission_id = await _fly_until_drop(r, task, cut=proxies[DROPPED])
            assert "lost" in r.events("agent_excluded", DROPPED)[0].message
            _, covered = await _retasked_to_the_end(r, mission_id, task)
    finally:
        for proxy in proxies.values():
            await proxy.stop()
    assert covered >= 99.0, covered


async def test_a_pilot_takeover_is_re_tasked_the_same_way(tmp_path: Path) -> None:
    task = _plan(tmp_path, "automatic")
    async with rig(tmp_path, 4, fleet_options={"pilot_links": True}) as r:
        station = await asyncio.to_thread(PilotStation, r.fleet.pilot_endpoints[1])
        try:
            await asyncio.to_thread(station.wait_heartbeat)

            async def take() -> None:  # the pilot's mode switch: LOITER holds where it is
                assert await asyncio.to_thread(station.set_mode, "LOITER") == 0

            mission_id = await _fly_until_drop(r, task, drop=take)
            assert r.daemon.authority.pilot(DROPPED) == "LOITER"
            assert "pilot" in r.events("agent_excluded", DROPPED)[0].message
            # The pilot lands it where it is: hovering at survey height on its share it would stand
            # in the way of whoever flies the rest (collision holds until their batteries run low).
            assert await asyncio.to_thread(station.set_mode, "LAND") == 0
            applied, covered = await _retasked_to_the_end(r, mission_id, task)
        finally:
            station.close()
    assert applied["dropped"] == DROPPED and DROPPED not in {g["ident"] for g in applied["legs"]}
    assert covered >= 99.0, covered
