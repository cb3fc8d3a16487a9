"""``/api/v1/missions``: list, submit a task file, progress, geometry, coverage, abort/pause/resume."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Query

from gcs.api_planning import task_paths
from gcs.http.deps import TOKEN, ApiProblem, Archive, Hub, Missions
from gcs.http.models import Coverage, MissionCreated, MissionGeometry, MissionSummary
from gcs.http.ports import MissionControl
from gcs.live import LiveHub
from gcs.missions import MissionProgress, MissionRejected
from protocol.taskfile import TaskFile, TaskFileError, parse_task_document

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
    return MissionGeometry(
        mission_id=mission_id, paths=task_paths(TaskFile.model_validate_json(stored.task_json))
    )


@router.get("/api/v1/missions/{mission_id}/coverage")
async def coverage(mission_id: str, control: Missions, hub: Hub) -> Coverage:
    progress_of(control, mission_id)
    planned = hub.plans.get(mission_id)
    tracks = {p.label: hub.track(p.label, mission_id) for p in planned.taskfile.plans} if planned else {}
    samples = sum(len(t) for t in tracks.values())
    if planned is None or planned.area is None or planned.swath_m is None:
        return Coverage(mission_id=mission_id, covered_pct=None, swath_m=None, samples=samples)
    pct = await asyncio.to_thread(_covered_pct, planned.area, list(tracks.values()), planned.swath_m)
    return Coverage(mission_id=mission_id, covered_pct=pct, swath_m=planned.swath_m, samples=samples)


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


def _covered_pct(
    area: list[tuple[float, float]], tracks: list[list[tuple[float, float]]], swath: float
) -> float:
    """Percent of ``area`` within swath/2 of the flown tracks (local frame of the area)."""
    import numpy as np
    import shapely
    from shapely.geometry import Polygon

    from gcs.planning.geodesy import LocalFrame

    arr = np.asarray(area)
    frame = LocalFrame.centred_on(arr[:, 0], arr[:, 1])
    poly = Polygon(frame.points_to_local(area)).buffer(0)
    lines = [shapely.linestrings(frame.points_to_local(t)) for t in tracks if len(t) > 1]
    if not lines or poly.area <= 0:
        return 0.0
    seen = shapely.union_all([shapely.buffer(line, swath / 2.0) for line in lines])
    return round(100.0 * poly.intersection(seen).area / poly.area, 2)
