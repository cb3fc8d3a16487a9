"""A survey's live progress for the operator (issue 27): seen share, flown distance, ETA, the raster.

Steps say "2/4" while 8 % or 84 % of the area is seen; this module says how much is seen and how
far each drone has flown of its plan, and when the survey should end: each drone still flying its
plan has ``planned - flown`` metres left (its final plan, re-task legs included, against its
thinned track, both horizontal, :mod:`gcs.missions.retask`), at its current ground speed (the
plan's speed while it turns or hovers); the mission's ETA is the slowest drone's.

:class:`CoverageFeed` gives the WebSocket one ``coverage`` message per running survey mission,
built from the retask service's records (every status tick's position, thinned to a metre) in a
worker thread: the live hub calls it at most once a second, never per status report. The raster
goes as two bit masks (``inside`` the area, ``seen``), row 0 south, packed with ``numpy.packbits``
and base64-encoded, with the grid's south-west and north-east corners, so a page draws it by
linear interpolation (a field is small enough for that).
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gcs.core.context import DaemonParts
    from gcs.missions.retask import SurveyRecord
    from gcs.missions.runner import MissionProgress
    from gcs.planning.seen import SeenGrid

DEFAULT_SPEED_MPS = 5.0  # a plan without a speed flies at the autopilot's default (WPNAV_SPEED 5 m/s)
MIN_MOVING_MPS = 1.0  # below it a drone turns, climbs or hovers: its plan's speed says more


@dataclass(frozen=True)
class DroneProgress:
    """One member's distance progress (horizontal metres)."""

    agent: str
    planned_m: float
    flown_m: float
    remaining_m: float
    speed_mps: float
    state: str  # flying, done, left

    def as_dict(self) -> dict[str, Any]:
        return {
            "agent": self.agent,
            "planned_m": round(self.planned_m, 1),
            "flown_m": round(self.flown_m, 1),
            "remaining_m": round(self.remaining_m, 1),
            "speed_mps": round(self.speed_mps, 2),
            "state": self.state,
        }


def distance_progress(
    rec: SurveyRecord,
    progress: MissionProgress,
    speeds: Mapping[str, float],
    flown_so_far: Mapping[str, float] | None = None,
) -> tuple[list[DroneProgress], float | None]:
    """Each member's planned, flown and remaining metres, and the mission's ETA in s (None: over,
    or nobody left flying its plan). ``speeds``: current ground speed per drone (m/s);
    ``flown_so_far``: metres already summed (:class:`LiveRaster`), else summed here."""
    from gcs.missions.retask import _speed, flown_m, planned_m

    members = {a.agent: a for a in progress.agents}
    drones: list[DroneProgress] = []
    eta: float | None = None
    for agent, plan in rec.planned.items():
        track = rec.tracks.get(agent, [])
        flown = flown_so_far[agent] if flown_so_far is not None and agent in flown_so_far else flown_m(track)
        home = (track[0][0], track[0][1]) if track else _home(plan, rec.survey.area[0])
        planned = planned_m(plan, home)
        member = members.get(agent)
        state = "left" if member is not None and member.excluded else "flying"
        if member is not None and member.done:
            state = "done"
        remaining = max(0.0, planned - flown) if state == "flying" else 0.0
        speed = float(speeds.get(agent, 0.0))
        use = speed if speed >= MIN_MOVING_MPS else (_speed(plan) or DEFAULT_SPEED_MPS)
        drones.append(DroneProgress(agent, planned, flown, remaining, speed, state))
        if state == "flying" and progress.state == "running":
            eta = max(eta or 0.0, remaining / use)
    return drones, eta


def distance_summary(
    rec: SurveyRecord,
    progress: MissionProgress,
    speeds: Mapping[str, float],
    flown_so_far: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The distance fields of a coverage answer (``GET .../coverage``, the stream's message)."""
    drones, eta = distance_progress(rec, progress, speeds, flown_so_far)
    return {
        "flown_m": round(sum(d.flown_m for d in drones), 1),
        "planned_m": round(sum(d.planned_m for d in drones), 1),
        "eta_s": None if eta is None else round(eta, 1),
        "drones": [d.as_dict() for d in drones],
    }


def _home(plan: list[Any], fallback: tuple[float, float]) -> tuple[float, float]:
    for a in plan:
        if getattr(a, "lat", None) is not None:
            return (a.lat, a.lon)
    return fallback


def _bits(mask: np.ndarray) -> str:
    return base64.b64encode(np.packbits(mask.astype(bool), axis=None).tobytes()).decode("ascii")


def raster(grid: SeenGrid) -> dict[str, Any]:
    """The grid for a page: corners (lat, lon), size, and the two masks as packed bits (base64)."""
    rows, cols = grid.inside.shape
    xs = np.array([grid.x0, grid.x0 + cols * grid.cell_m])
    ys = np.array([grid.y0, grid.y0 + rows * grid.cell_m])
    lat, lon = grid.frame.to_geodetic(xs, ys)
    return {
        "sw": [round(float(lat[0]), 7), round(float(lon[0]), 7)],
        "ne": [round(float(lat[1]), 7), round(float(lon[1]), 7)],
        "rows": rows,
        "cols": cols,
        "cell_m": round(grid.cell_m, 3),
        "inside": _bits(grid.inside),
        "seen": _bits(grid.inside & grid.seen),
    }


def unpack_mask(text: str, rows: int, cols: int) -> np.ndarray:
    """A mask of :func:`raster` back as a (rows, cols) bool array (tests, Python clients)."""
    bits = np.unpackbits(np.frombuffer(base64.b64decode(text), dtype=np.uint8))
    return bits[: rows * cols].reshape(rows, cols).astype(bool)


@dataclass
class LiveRaster:
    """One mission's seen grid kept between messages: each call sweeps only the track points
    added since (a track is append-only), so a message costs the last second's segments, not the
    whole flight (the same cells as rasterising every track at once: the capsules of the same
    segments)."""

    grid: SeenGrid
    swept: dict[str, int] = field(default_factory=dict)  # agent -> track points swept so far
    flown: dict[str, float] = field(default_factory=dict)  # agent -> metres of those points

    @classmethod
    def of(cls, rec: SurveyRecord) -> LiveRaster:
        from gcs.planning.seen import seen_grid

        survey = rec.survey
        return cls(seen_grid(survey.area, [], survey.swath_m, survey.altitude_m))

    def update(self, rec: SurveyRecord) -> SeenGrid:
        from gcs.missions.retask import flown_m
        from gcs.planning.seen import footprint_half_widths, sweep

        g, survey = self.grid, rec.survey
        for agent, track in rec.tracks.items():
            done = self.swept.get(agent, 0)
            if len(track) <= done:
                continue
            points = track[max(0, done - 1) :]  # from the last one swept: the segment joining them
            self.flown[agent] = self.flown.get(agent, 0.0) + flown_m(points)
            tail = np.asarray(points, dtype=float).reshape(-1, 3)
            pts = g.frame.points_to_local([(float(a), float(b)) for a, b in tail[:, :2]])
            half = footprint_half_widths(tail[:, 2], survey.swath_m, survey.altitude_m)
            sweep(g.seen, pts, half, g.x0, g.y0, g.cell_m)
            self.swept[agent] = len(track)
        return g


def coverage_message(
    rec: SurveyRecord,
    progress: MissionProgress,
    speeds: Mapping[str, float],
    live: LiveRaster | None = None,
) -> str:
    """The WebSocket ``coverage`` message of one mission, as JSON text (CPU work: a worker thread);
    with ``live`` the raster is brought up to date rather than computed anew."""
    survey = rec.survey
    live = live or LiveRaster.of(rec)
    grid = live.update(rec)
    message = {
        "type": "coverage",
        "mission_id": rec.mission_id,
        "state": progress.state,
        "covered_pct": grid.covered_pct,
        "area_m2": round(grid.area_m2, 1),
        "seen_m2": round(grid.seen_m2, 1),
        "swath_m": survey.swath_m,
        **distance_summary(rec, progress, speeds, live.flown),
        "grid": raster(grid),
    }
    return json.dumps(message, separators=(",", ":"))


def ground_speed(status: Any) -> float:
    """Horizontal speed of a status report (m/s), 0 without one."""
    if status is None:
        return 0.0
    return math.hypot(status.velocity.vn, status.velocity.ve)


class CoverageFeed:
    """The live hub's source of ``coverage`` messages: one per running survey mission with a record."""

    def __init__(self, daemon: DaemonParts) -> None:
        self._daemon = daemon
        self._running: set[str] = set()  # surveys running at the last call: an ended one gets a last message
        self._rasters: dict[str, LiveRaster] = {}  # mission id -> its raster so far

    def _retask(self) -> Any:
        from gcs.missions.retask import Retasking

        return next((s for s in self._daemon.services if isinstance(s, Retasking)), None)

    async def messages(self) -> list[tuple[str, str]]:
        """(mission id, message text) for every running survey, and once more for one that ended
        since the last call (its final share, no ETA); the raster in a worker thread."""
        retask = self._retask()
        if retask is None:
            return []
        active = self._daemon.missions.active
        running = {m for m, a in active.items() if a.task.survey is not None and a.state == "running"}
        ended, self._running = self._running - running, running
        jobs: list[tuple[str, SurveyRecord, MissionProgress, dict[str, float], LiveRaster | None]] = []
        for mission_id in sorted(running | ended):
            rec = retask.record(mission_id) if mission_id in running else retask.records.get(mission_id)
            progress = self._daemon.missions.progress(mission_id)
            if rec is None or progress is None:
                continue
            speeds = {}
            for agent in rec.planned:
                session = self._daemon.agents.session(agent)
                speeds[agent] = ground_speed(session.status if session is not None else None)
            jobs.append((mission_id, rec.snapshot(), progress, speeds, self._rasters.get(mission_id)))
        for mission_id in [m for m in self._rasters if m not in running]:
            del self._rasters[mission_id]
        if not jobs:
            return []
        return await asyncio.to_thread(self._build, jobs, running)

    def _build(
        self,
        jobs: list[tuple[str, SurveyRecord, MissionProgress, dict[str, float], LiveRaster | None]],
        running: set[str],
    ) -> list[tuple[str, str]]:
        """In the worker thread (one call at a time: the hub awaits each): the messages, and the
        rasters of the running surveys kept for the next call."""
        out = []
        for mission_id, rec, progress, speeds, live in jobs:
            live = live or LiveRaster.of(rec)
            out.append((mission_id, coverage_message(rec, progress, speeds, live)))
            if mission_id in running:
                self._rasters[mission_id] = live
        return out
