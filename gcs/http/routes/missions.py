"""``/api/v1/missions``: list, submit a task file, progress, geometry, coverage, abort/pause/resume."""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Query
from pydantic import BaseModel, ConfigDict, Field

from gcs.http.deps import TOKEN, ApiProblem, Archive, Hub, Missions, Ports, Retask
from gcs.http.models import Coverage, MissionCreated, MissionGeometry, MissionSummary
from gcs.http.planning_requests import task_paths
from gcs.http.ports import MissionArchive, MissionControl
from gcs.missions.mission_files import MAX_FILES, task_from_mission_files
from gcs.missions.report import CoverageReport, build_report
from gcs.missions.retask import RetaskError
from gcs.missions.runner import MissionProgress, MissionRejected, stored_task
from gcs.observe.live import LiveHub
from protocol.taskfile import SurveyArea, TaskFile, TaskFileError, parse_task_document

router = APIRouter()
TASK_DOCUMENT_SCHEMA: dict[str, Any] = {
    "description": "a fleetgcs task file (object) or a CoUAS task file (array of action rows)",
    "oneOf": [{"$ref": "#/components/schemas/TaskFile"}, {"type": "array", "items": {"type": "object"}}],
}


async def submit_task(missions: MissionControl, task: TaskFile) -> str:
    """Start ``task`` as a mission; a refusal (fleet, task rules) is a 422 with the reason."""
    try:
        return await missions.submit(task)
    except MissionRejected as exc:
        raise ApiProblem(422, "mission rejected", str(exc)) from None


def progress_of(missions: MissionControl, mission_id: str) -> MissionProgress:
    progress = missions.progress(mission_id)
    if progress is None:
        raise ApiProblem(404, "no such mission", f"mission {mission_id!r} does not exist")
    return progress


@router.get("/api/v1/missions")
async def missions(
    archive: Archive,
    state: Literal["running", "completed", "aborted"] | None = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
) -> list[MissionSummary]:
    rows = archive.missions(state)[-limit:][::-1]
    return [
        MissionSummary(
            id=m.id, name=m.name, state=m.state, created=m.created, finished=m.finished, result=m.result
        )
        for m in rows
    ]


@router.post("/api/v1/missions", status_code=201, dependencies=TOKEN)
async def submit(
    control: Missions,
    document: Any = Body(..., description=TASK_DOCUMENT_SCHEMA["description"]),  # noqa: B008
) -> MissionCreated:
    """Submit a fleetgcs task file or a CoUAS task file (validated against the live fleet)."""
    try:
        task = parse_task_document(document)
    except (TaskFileError, ValueError, TypeError) as exc:
        raise ApiProblem(422, "invalid task file", str(exc)[:1000]) from None
    return MissionCreated(mission_id=await submit_task(control, task))


class MissionImport(BaseModel):
    """One drone's QGC ``.plan`` or Mission Planner ``.waypoints`` per file; the file name names the drone."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(default="imported-mission", min_length=1, max_length=128)
    files: dict[str, str] = Field(
        min_length=1,
        max_length=MAX_FILES,
        description='file name -> text, e.g. {"drone-1.plan": "{...}", "drone-2.waypoints": "QGC WPL 110"}',
    )
    allow_airborne_end: bool = False


@router.post("/api/v1/missions/import", status_code=201, dependencies=TOKEN)
async def import_mission(control: Missions, request: MissionImport) -> MissionCreated:
    """Fly QGroundControl ``.plan`` / Mission Planner ``.waypoints`` files, one per drone."""
    try:
        task = task_from_mission_files(
            request.files, request.name, allow_airborne_end=request.allow_airborne_end
        )
    except (TaskFileError, ValueError) as exc:
        raise ApiProblem(422, "invalid mission file", str(exc)[:1000]) from None
    return MissionCreated(mission_id=await submit_task(control, task))


@router.get("/api/v1/missions/{mission_id}")
async def mission(mission_id: str, control: Missions) -> MissionProgress:
    return progress_of(control, mission_id)


@router.get("/api/v1/missions/{mission_id}/plan")
async def mission_geometry(mission_id: str, archive: Archive, hub: Hub) -> MissionGeometry:
    planned = hub.plans.get(mission_id)
    stored = archive.mission(mission_id)
    if stored is None:
        raise ApiProblem(404, "no such mission", f"mission {mission_id!r} does not exist")
    if planned is not None:
        return MissionGeometry(
            mission_id=mission_id,
            paths={d.agent: d.points for d in planned.drones},
            area=planned.area,
            targets=planned.targets,
            swath_m=planned.swath_m,
        )
    task = _stored_task(mission_id, stored.task_json)
    if task is None:  # stored by a version whose task this one cannot read
        return MissionGeometry(mission_id=mission_id, paths={})
    survey = task.survey  # a planned task file submitted as a file (gcs plan + gcs run) carries its area
    return MissionGeometry(
        mission_id=mission_id,
        paths=task_paths(task),
        area=survey.area if survey else None,
        swath_m=survey.swath_m if survey else None,
    )


@router.get("/api/v1/missions/{mission_id}/coverage")
async def coverage(
    mission_id: str,
    control: Missions,
    archive: Archive,
    hub: Hub,
    ports: Ports,
    detail: Annotated[
        Literal["none", "grid", "geojson"],
        Query(description="grid: seen/unseen text rows; geojson: the unseen cells as a MultiPolygon"),
    ] = "none",
) -> Coverage:
    """Seen share of the mission's area from the flown tracks (position, height, eq. 5 footprint);
    for a survey this daemon flies, the distance planned and flown per drone and the ETA."""
    progress = progress_of(control, mission_id)
    survey = _survey(mission_id, archive, hub)
    labels = [p.label for p in survey[1].plans] if survey else []
    tracks = [hub.track3d(label, mission_id) for label in labels]
    samples = sum(len(t) for t in tracks)
    if survey is None or survey[0] is None:
        return Coverage(mission_id=mission_id, covered_pct=None, swath_m=None, samples=samples)
    from gcs.planning.seen import seen_grid  # numpy/geodesy only when a map is asked for

    area = survey[0]
    grid = await asyncio.to_thread(seen_grid, area.area, tracks, area.swath_m, area.altitude_m)
    rec = ports.retask.record(mission_id) if ports.retask is not None else None
    distance: dict[str, Any] = {}
    if rec is not None:
        from gcs.missions.live_coverage import distance_summary, ground_speed

        sessions = ports.agents.sessions
        speeds = {a: ground_speed(s.status) for a in rec.planned if (s := sessions.get(a)) is not None}
        distance = await asyncio.to_thread(distance_summary, rec.snapshot(), progress, speeds)
    return Coverage(
        **distance,
        mission_id=mission_id,
        covered_pct=grid.covered_pct,
        swath_m=area.swath_m,
        samples=samples,
        area_m2=round(grid.area_m2, 1),
        seen_m2=round(grid.seen_m2, 1),
        cell_m=round(grid.cell_m, 3),
        grid=grid.rows() if detail == "grid" else None,
        unseen=grid.unseen_geojson() if detail == "geojson" else None,
    )


def _survey(
    mission_id: str, archive: MissionArchive, hub: LiveHub
) -> tuple[SurveyArea | None, TaskFile] | None:
    """The mission's surveyed area (a plan started from the API, or the task file's own) and task."""
    planned = hub.plans.get(mission_id)
    if planned is not None:
        task: TaskFile = planned.taskfile
        if task.survey is None and planned.area is not None and planned.swath_m is not None:
            return SurveyArea(area=planned.area, swath_m=planned.swath_m), task
        return task.survey, task
    stored = archive.mission(mission_id)
    if stored is None:
        return None
    stored_one = _stored_task(mission_id, stored.task_json)
    return None if stored_one is None else (stored_one.survey, stored_one)


@functools.lru_cache(maxsize=32)
def _stored_task(mission_id: str, task_json: str) -> TaskFile | None:
    """Parsed once per mission: coverage is polled every second or so while a survey flies (None:
    stored by a version whose task this one cannot read)."""
    return stored_task(task_json)


@router.get("/api/v1/missions/{mission_id}/retask")
async def retask_proposals(mission_id: str, control: Missions, retask: Retask) -> list[dict[str, Any]]:
    """The mission's re-task decisions: a dropped drone's unseen share, the legs proposed for the
    others (predicted time and energy each) and what became of them (pending, applied, rejected)."""
    progress_of(control, mission_id)
    return retask.proposals(mission_id)


@router.post("/api/v1/missions/{mission_id}/retask/{decision_id}/{answer}", dependencies=TOKEN)
async def retask_decide(
    mission_id: str, decision_id: str, answer: Literal["accept", "reject"], control: Missions, retask: Retask
) -> dict[str, Any]:
    """Accept (fly it through the vehicle authority at mission priority) or reject a pending
    proposal; ``decision_id`` ``latest`` is the newest pending one."""
    progress_of(control, mission_id)
    try:
        decision = retask.decide(
            mission_id, None if decision_id == "latest" else decision_id, answer == "accept"
        )
    except RetaskError as exc:
        raise ApiProblem(409, "no such pending proposal", str(exc)) from None
    return decision.summary(gap=True)


@router.get("/api/v1/missions/{mission_id}/report")
async def report(mission_id: str, control: Missions, retask: Retask) -> CoverageReport:
    """Coverage report of a survey mission: coverage %, the missed area (GeoJSON), per-drone
    planned vs flown metres, the re-task decisions and the gaps they left, named."""
    progress = progress_of(control, mission_id)
    rec = await retask.find(mission_id)  # in memory, or kept in the store across a restart
    if rec is None:
        raise ApiProblem(404, "no coverage record", f"mission {mission_id!r} is no survey this daemon flew")
    left = {a.agent: (a.why or "excluded") if a.excluded else None for a in progress.agents}
    return await asyncio.to_thread(build_report, rec, progress.state, left)


@router.post("/api/v1/missions/{mission_id}/abort", dependencies=TOKEN)
async def abort(
    mission_id: str,
    control: Missions,
    hub: Hub,
    then: Annotated[
        Literal["rtl", "hold", "land"],
        Query(description="rtl: fly home, deconflicted (default); hold: stop where they are; land"),
    ] = "rtl",
) -> MissionProgress:
    started = time.perf_counter()
    progress = await _mission_command(
        control,
        mission_id,
        lambda m: control.abort(m, f"aborted by the operator ({then})", "operator", then),
    )
    hub.metrics.command_latency.labels(f"abort_{then}").observe(time.perf_counter() - started)
    return progress


@router.post("/api/v1/missions/{mission_id}/pause", dependencies=TOKEN)
async def pause(mission_id: str, control: Missions, hub: Hub) -> MissionProgress:
    return await _timed(hub, "pause", _mission_command(control, mission_id, control.pause))


@router.post("/api/v1/missions/{mission_id}/resume", dependencies=TOKEN)
async def resume(mission_id: str, control: Missions, hub: Hub) -> MissionProgress:
    return await _timed(hub, "resume", _mission_command(control, mission_id, control.resume))


async def _timed(hub: LiveHub, name: str, command: Awaitable[MissionProgress]) -> MissionProgress:
    started = time.perf_counter()
    result = await command
    hub.metrics.command_latency.labels(name).observe(time.perf_counter() - started)
    return result


async def _mission_command(
    control: MissionControl, mission_id: str, command: Callable[[str], Awaitable[object]]
) -> MissionProgress:
    progress_of(control, mission_id)
    try:
        await command(mission_id)
    except MissionRejected as exc:
        raise ApiProblem(409, "mission not running", str(exc)) from None
    return progress_of(control, mission_id)
