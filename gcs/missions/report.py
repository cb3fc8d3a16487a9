"""A survey mission's coverage report (issue 27): what was seen, what was missed and why.

Built from the retask service's record of the mission (gcs/missions/retask.py: the flown tracks,
the plans as they ended up, the re-task decisions) by the same raster as the live coverage map
(:func:`gcs.planning.seen.seen_grid`). A gap left by a rejected or infeasible proposal is named
with its area and its reason, so "why is this part unseen" has an answer in the report.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, Field

if TYPE_CHECKING:  # the client imports the model; shapely and scipy only where a report is built
    from gcs.missions.retask import SurveyRecord


class DroneReport(BaseModel):
    agent: str
    planned_m: float = Field(description="horizontal metres of its final plan (re-task legs included)")
    flown_m: float = Field(description="horizontal metres of its flown track in this mission")
    added_m: float = Field(default=0.0, description="survey metres re-tasked to it from a dropped drone")
    left: str | None = Field(default=None, description="why it left the mission early (None: it did not)")


class GapReport(BaseModel):
    decision: str
    dropped: str
    state: str = Field(description="rejected, pending (never decided), or none (not feasible)")
    gap_m2: float
    reason: str
    gap: dict[str, Any] = Field(description="the dropped share's unseen cells, GeoJSON MultiPolygon")


class CoverageReport(BaseModel):
    mission_id: str
    state: str
    covered_pct: float
    area_m2: float
    seen_m2: float
    swath_m: float
    missed: dict[str, Any] = Field(description="every unseen cell of the area, GeoJSON MultiPolygon")
    drones: list[DroneReport]
    retask: list[dict[str, Any]] = Field(description="the re-task decisions, oldest first")
    gaps: list[GapReport] = Field(description="dropped shares left unseen by a decision, named")


def build_report(rec: SurveyRecord, state: str, left: Mapping[str, str | None]) -> CoverageReport:
    """The report of one mission (CPU work: call it in a worker thread)."""
    from gcs.missions.retask import flown_m, planned_m
    from gcs.planning.seen import seen_grid

    survey = rec.survey
    grid = seen_grid(survey.area, list(rec.tracks.values()), survey.swath_m, survey.altitude_m)
    added: dict[str, float] = {}
    for d in rec.decisions:
        if d.state == "applied":
            for leg in d.proposal.legs:
                added[leg.ident] = added.get(leg.ident, 0.0) + leg.survey_m
    left = dict(left)
    for d in rec.decisions:  # the runner keeps no reason once the mission is over; the decision does
        if left.get(d.dropped) in (None, "excluded"):
            left[d.dropped] = d.why
    drones = []
    for agent, plan in rec.planned.items():
        track = rec.tracks.get(agent, [])
        home = (track[0][0], track[0][1]) if track else _first_point(plan, survey.area[0])
        drones.append(
            DroneReport(
                agent=agent,
                planned_m=round(planned_m(plan, home), 1),
                flown_m=round(flown_m(track), 1),
                added_m=round(added.get(agent, 0.0), 1),
                left=left.get(agent),
            )
        )
    gaps = [
        GapReport(
            decision=d.id,
            dropped=d.dropped,
            state=d.state,
            gap_m2=d.proposal.gap_m2,
            reason=d.proposal.reason if d.state != "rejected" else f"proposal rejected by the {d.by}",
            gap=d.proposal.gap,
        )
        for d in rec.decisions
        if d.state in ("rejected", "pending") or d.proposal.verdict == "not_feasible"
    ]
    return CoverageReport(
        mission_id=rec.mission_id,
        state=state,
        covered_pct=grid.covered_pct,
        area_m2=round(grid.area_m2, 1),
        seen_m2=round(grid.seen_m2, 1),
        swath_m=survey.swath_m,
        missed=grid.unseen_geojson(),
        drones=drones,
        retask=[d.summary() for d in rec.decisions],
        gaps=gaps,
    )


def _first_point(plan: list[Any], fallback: tuple[float, float]) -> tuple[float, float]:
    for a in plan:
        if hasattr(a, "lat") and a.lat is not None:
            return (a.lat, a.lon)
    return fallback


def render_report(report: CoverageReport) -> list[str]:
    """The report as text lines (``gcs mission report``), within 100 columns."""
    lines = [
        f"mission {report.mission_id} ({report.state}): {report.covered_pct:.1f} % of "
        f"{report.area_m2:,.0f} m2 seen (swath {report.swath_m:g} m)",
        f"{'drone':12} {'planned m':>10} {'flown m':>10} {'re-tasked m':>12}  left",
    ]
    for d in report.drones:
        lines.append(f"{d.agent:12} {d.planned_m:10.0f} {d.flown_m:10.0f} {d.added_m:12.0f}  {d.left or ''}")
    for r in report.retask:
        legs = ", ".join(
            f"{g['ident']} {g['survey_m']:.0f} m {g['time_s']:.0f} s {g['energy_wh']:.1f} Wh"
            for g in r["legs"]
        )
        lines.append(
            f"re-task {r['id']} ({r['dropped']}): {r['state']}, {r['reason']}"
            + (f" [{legs}]" if legs else "")
        )
    for g in report.gaps:
        lines.append(f"gap {g.decision}: {g.gap_m2:,.0f} m2 of {g.dropped}'s share unseen: {g.reason}")
    return lines
