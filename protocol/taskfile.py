"""The mission task file: per-agent ordered actions with sync points (JSON, pydantic schema).

Two formats are read:

* the fleetgcs task file (:class:`TaskFile`, ``"format": "fleetgcs-task"``), documented in
  ``docs/protocol.md``;
* the original CoUAS task file: a JSON array of objects with ``Action_type`` (0 arm-and-takeoff
  ``Alt``; 1 go-to ``Lat``/``Lon``/``Alt``; 2 go-by ``N``/``E`` at altitude ``Alt``; 3 land
  ``Lat``/``Lon`` with 0,0 meaning "here"), ``CID``, ``Step``, ``Sync`` and optional ``Time``.
  Each drone flies its rows in file order; sync points match by their order (see
  :func:`from_couas` and ``docs/protocol.md``).

Validation makes the barrier service safe by construction: every agent's plan starts with a
takeoff, steps never go backwards, and every agent has the same sequence of sync steps, so no
barrier can wait on an agent that will never reach it. A task document that comes in
(:func:`parse_task_document`) must also end every plan on the ground (land or rtl) unless it
allows an airborne end explicitly.
"""

from __future__ import annotations

import itertools
import json
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from protocol.actions import Action, GoBy, Goto, Land, Takeoff
from protocol.gcj02 import gcj02_to_wgs84


class TaskFileError(ValueError):
    """A task file that cannot be flown; the message says what and where."""


class AgentPlan(BaseModel):
    """The ordered actions of one agent, addressed by identity name or by connection ID."""

    model_config = ConfigDict(extra="forbid")

    agent: str | None = Field(default=None, min_length=1, max_length=64, description="agent identity")
    cid: int | None = Field(default=None, ge=1, le=65_535, description="connection ID (CoUAS files)")
    actions: list[Action] = Field(min_length=1, max_length=10_000)

    @model_validator(mode="after")
    def _addressed_once(self) -> AgentPlan:
        if (self.agent is None) == (self.cid is None):
            raise ValueError("each agent plan needs exactly one of 'agent' (identity) or 'cid'")
        return self

    @property
    def label(self) -> str:
        """How errors and logs name this plan."""
        return self.agent if self.agent is not None else f"cid {self.cid}"

    def sync_steps(self) -> list[int]:
        """The steps after which this agent waits at a barrier, in order."""
        return [a.step for a in self.actions if a.sync]


class SurveyArea(BaseModel):
    """The area a survey mission covers and its sensor footprint: the daemon's live coverage map.

    Optional: planners (``gcs plan``, the API's plan) fill it so that a mission submitted as a
    file still shows its area, swath band and seen/unseen map.
    """

    model_config = ConfigDict(extra="forbid")

    area: list[tuple[float, float]] = Field(min_length=3, max_length=10_000, description="[lat, lon] ring")
    swath_m: float = Field(gt=0.0, le=5000.0, description="ground width seen across track at altitude_m")
    altitude_m: float | None = Field(default=None, gt=0.0, le=10_000.0, description="planned survey height")
    retask: Literal["ask", "automatic", "off"] = Field(
        default="ask",
        description="a drone leaves the survey: propose its unseen share to the others and wait for the "
        "operator (ask), fly the proposal at once (automatic), or do nothing (off)",
    )

    @model_validator(mode="after")
    def _latlon(self) -> SurveyArea:
        for lat, lon in self.area:
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
                raise ValueError(f"survey area vertex ({lat}, {lon}) is not a lat/lon in degrees")
        return self


class TaskFile(BaseModel):
    """A whole mission."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["fleetgcs-task"] = "fleetgcs-task"
    version: Literal[1] = 1
    name: str = Field(default="mission", min_length=1, max_length=128)
    sync_timeout_s: float = Field(default=120.0, gt=0.0, le=86_400.0)
    lost_agent_policy: Literal["abort", "continue"] = "abort"
    on_action_failed: Literal["end", "skip", "retry"] = Field(
        default="end",
        description="an agent's action failed (e.g. refused by its autopilot): end the mission "
        "(everyone returns to launch), skip that action, or retry it (then end)",
    )
    action_retries: int = Field(default=1, ge=0, le=10, description="retries per failed step (retry)")
    fix_wait_s: float = Field(
        default=60.0, ge=0.0, le=600.0, description="pre-flight: wait this long for every agent's 3-D fix"
    )
    allow_airborne_end: bool = Field(
        default=False,
        description="accept plans whose last action is not a land or rtl (the drone stays armed in the air)",
    )
    plans: list[AgentPlan] = Field(min_length=1, max_length=1000)
    survey: SurveyArea | None = Field(default=None, description="surveyed area and footprint (coverage map)")

    @model_validator(mode="after")
    def _flyable(self) -> TaskFile:
        validate_plans(self.plans)
        return self


LANDING_KINDS = ("land", "rtl")


def airborne_plans(plans: list[AgentPlan]) -> list[str]:
    """Labels of the plans that end with the drone still in the air (no final land or rtl)."""
    return [p.label for p in plans if p.actions[-1].kind not in LANDING_KINDS]


def task_warnings(task: TaskFile) -> list[str]:
    """What an operator should read before flying ``task`` (it is valid, but maybe not meant)."""
    airborne = airborne_plans(task.plans)
    if not airborne:
        return []
    return [
        f"{', '.join(airborne)} never land: the mission completes with the drone armed in the air "
        "(allowed by allow_airborne_end)"
    ]


def require_landing(task: TaskFile) -> None:
    """Refuse a task whose drones would stay armed in the air, unless it allows that explicitly.

    Checked where task documents come in (:func:`parse_task_document`: the API, ``gcs run``),
    not in the model itself, so missions stored by older versions still load.
    """
    airborne = airborne_plans(task.plans)
    if airborne and not task.allow_airborne_end:
        raise TaskFileError(
            f"{', '.join(airborne)}: the last action is not a land or rtl, so the drone would stay "
            "armed in the air after the mission completes; add a land, or set allow_airborne_end "
            "(gcs run --allow-airborne-end) if that is meant"
        )


def validate_plans(plans: list[AgentPlan]) -> None:
    """Raise ValueError unless the plans can be flown without a barrier deadlock."""
    seen: set[str] = set()
    reference: tuple[str, list[int]] | None = None
    for plan in plans:
        if plan.label in seen:
            raise ValueError(f"{plan.label} appears in more than one plan")
        seen.add(plan.label)
        if not isinstance(plan.actions[0], Takeoff):
            raise ValueError(f"{plan.label}: the first action must be a takeoff, not {plan.actions[0].kind}")
        last = -1
        for index, action in enumerate(plan.actions):
            if action.step < last:
                raise ValueError(
                    f"{plan.label}: action {index} has step {action.step} after step {last}; "
                    "steps must not decrease"
                )
            last = action.step
        syncs = plan.sync_steps()
        if len(set(syncs)) != len(syncs):
            raise ValueError(f"{plan.label}: more than one sync point at the same step {syncs}")
        if reference is None:
            reference = (plan.label, syncs)
        elif syncs != reference[1]:
            raise ValueError(
                f"unequal sync points: {reference[0]} syncs at steps {reference[1]} but "
                f"{plan.label} at {syncs}; every agent must have the same sync steps"
            )


class _CouasRow(BaseModel):
    """One row of a CoUAS task file (field names as the original GUI writes them)."""

    model_config = ConfigDict(extra="ignore")

    Action_type: int
    CID: int = Field(ge=1, le=65_535)
    Step: int = Field(ge=0)
    Sync: int | bool = 0
    Time: float | None = None
    Alt: float | None = None
    Lat: float | None = None
    Lon: float | None = None
    N: float | None = None
    E: float | None = None


COUAS_ACTION_TYPES = {0: "arm-and-takeoff", 1: "go-to", 2: "go-by", 3: "land"}


def _a(action_type: int) -> str:
    name = COUAS_ACTION_TYPES[action_type]
    return f"an {name}" if name[0] in "aeiou" else f"a {name}"


class _Row:
    """A validated CoUAS row with its place in the file (numbered from 1, as an editor shows it)."""

    __slots__ = ("number", "row")

    def __init__(self, number: int, row: _CouasRow) -> None:
        self.number = number
        self.row = row

    @property
    def where(self) -> str:
        return f"row {self.number} (CID {self.row.CID}, Step {self.row.Step})"


def _rows_text(rows: list[_Row]) -> str:
    return ", ".join(str(r.number) for r in rows) or "none"


def _check_couas_drone(cid: int, rows: list[_Row], allow_airborne_end: bool) -> None:
    """The CoUAS rules for one drone's rows in file order, with errors naming the rows."""
    first = rows[0]
    if first.row.Action_type != 0:
        raise TaskFileError(
            f"CoUAS {first.where}: the first action must be a takeoff, but CID {cid} starts with "
            f"{_a(first.row.Action_type)} (a drone's first row in the file must be Action_type 0)"
        )
    by_step: dict[int, _Row] = {}
    for entry in rows:
        earlier = by_step.get(entry.row.Step)
        if earlier is not None:
            raise TaskFileError(
                f"CoUAS rows {earlier.number} and {entry.number}: CID {cid} uses Step {entry.row.Step} twice "
                "(the step numbers restart); each row of a drone needs its own Step"
            )
        by_step[entry.row.Step] = entry
    last = rows[-1]
    if last.row.Action_type != 3 and not allow_airborne_end:
        raise TaskFileError(
            f"CoUAS {last.where}: CID {cid} never lands (its last row is {_a(last.row.Action_type)}), "
            "so the drone would stay armed in the air after "
            "the mission completes; end it with a land (Action_type 3), or allow it explicitly "
            "(gcs run --allow-airborne-end)"
        )


def _couas_actions(rows: list[_Row], gcj02: bool) -> list[Any]:
    """One drone's rows (file order) as actions; go-by ``Alt`` is the altitude to fly at."""
    actions: list[Any] = []
    flying_alt = 0.0  # the altitude the previous row commanded, above home

    def need(entry: _Row, name: str, value: float | None) -> float:
        if value is None:
            raise TaskFileError(f"CoUAS {entry.where}: {_a(entry.row.Action_type)} row lacks '{name}'")
        return value

    def position(entry: _Row, lat: float, lon: float) -> tuple[float, float]:
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise TaskFileError(f"CoUAS {entry.where}: Lat {lat}, Lon {lon} is not a position on Earth")
        return gcj02_to_wgs84(lat, lon) if gcj02 else (lat, lon)

    def altitude(entry: _Row) -> float:
        alt = need(entry, "Alt", entry.row.Alt)
        if alt <= 0.0:
            raise TaskFileError(
                f"CoUAS {entry.where}: Alt {alt} m; Alt is the altitude to fly at (metres above home) "
                "and must be above 0"
            )
        return alt

    for entry in rows:
        try:
            row = entry.row
            step, sync = 0, bool(row.Sync)  # steps are assigned afterwards (see _couas_steps)
            if row.Action_type == 0:
                flying_alt = altitude(entry)
                actions.append(Takeoff(alt=flying_alt, step=step, sync=sync))
            elif row.Action_type == 1:
                lat, lon = position(entry, need(entry, "Lat", row.Lat), need(entry, "Lon", row.Lon))
                flying_alt = altitude(entry)
                actions.append(Goto(lat=lat, lon=lon, alt=flying_alt, step=step, sync=sync))
            elif row.Action_type == 2:
                # CoUAS flies a go-by at Alt (its MAVProxy agent) or holds altitude (its DroneKit agent);
                # in every original file Alt equals the takeoff altitude. Without Alt: hold altitude.
                target = flying_alt if row.Alt is None else altitude(entry)
                up = target - flying_alt
                flying_alt = target
                north, east = need(entry, "N", row.N), need(entry, "E", row.E)
                actions.append(GoBy(north=north, east=east, up=up, step=step, sync=sync))
            else:
                lat, lon = row.Lat or 0.0, row.Lon or 0.0
                flying_alt = 0.0
                if lat == 0.0 and lon == 0.0:
                    actions.append(Land(step=step, sync=sync))
                else:
                    lat, lon = position(entry, lat, lon)
                    actions.append(Land(lat=lat, lon=lon, step=step, sync=sync))
        except ValidationError as exc:
            raise TaskFileError(f"CoUAS {entry.where}: {first_error(exc)}") from None
    return actions


def _couas_steps(drones: dict[int, list[_Row]]) -> dict[int, list[int]]:
    """Mission steps for each drone's rows in file order, with the k-th sync of every drone on one step.

    CoUAS flies rows in file order, echoes ``Step`` back as a label, and matches sync points by
    their order (its monitor sends one sub-task per sync). When each drone's Steps already rise in
    file order and the drones sync at equal Steps, the file's Steps are kept; otherwise rows are
    renumbered: segment k (the rows up to and including each drone's k-th sync) takes as many
    steps as its longest drone needs, and every drone's k-th sync gets the segment's last step.
    """
    rising = all(
        all(a.row.Step < b.row.Step for a, b in itertools.pairwise(rows)) for rows in drones.values()
    )
    syncs = {cid: [r.row.Step for r in rows if r.row.Sync] for cid, rows in drones.items()}
    if rising and len({tuple(s) for s in syncs.values()}) == 1:
        return {cid: [r.row.Step for r in rows] for cid, rows in drones.items()}
    segments: dict[int, list[list[_Row]]] = {}
    for cid, rows in drones.items():
        parts: list[list[_Row]] = [[]]
        for entry in rows:
            parts[-1].append(entry)
            if entry.row.Sync:
                parts.append([])
        segments[cid] = parts
    count = max(len(parts) for parts in segments.values())
    steps: dict[int, list[int]] = {cid: [] for cid in drones}
    base = 0
    for k in range(count):
        width = max(len(parts[k]) if k < len(parts) else 0 for parts in segments.values())
        for cid, parts in segments.items():
            if k >= len(parts):
                continue
            for i, entry in enumerate(parts[k]):
                steps[cid].append(base + width - 1 if entry.row.Sync else base + i)
        base += width
    return steps


def from_couas(
    rows: list[Any],
    name: str = "couas-mission",
    *,
    allow_airborne_end: bool = False,
    gcj02: bool = False,
) -> TaskFile:
    """Convert an original CoUAS task file (already parsed JSON) into a :class:`TaskFile`.

    ``gcj02``: go-to and land coordinates are GCJ-02 (Chinese web maps); convert them to WGS-84.
    ``allow_airborne_end``: accept drones that never land (refused otherwise).
    """
    if not isinstance(rows, list) or not rows:
        raise TaskFileError("a CoUAS task file is a non-empty JSON array of action objects")
    drones: dict[int, list[_Row]] = {}
    for index, raw in enumerate(rows):
        number = index + 1
        try:
            row = _CouasRow.model_validate(raw)
        except ValidationError as exc:
            raise TaskFileError(f"CoUAS row {number}: {first_error(exc)}") from None
        if row.Action_type not in COUAS_ACTION_TYPES:
            types = ", ".join(f"{k} {v}" for k, v in COUAS_ACTION_TYPES.items())
            raise TaskFileError(
                f"CoUAS row {number} (CID {row.CID}, Step {row.Step}): Action_type {row.Action_type} "
                f"is not one of {types}"
            )
        drones.setdefault(row.CID, []).append(_Row(number, row))
    actions = {cid: _couas_actions(drone_rows, gcj02) for cid, drone_rows in drones.items()}
    for cid, drone_rows in drones.items():
        _check_couas_drone(cid, drone_rows, allow_airborne_end)
    sync_rows = {cid: [r for r in drone_rows if r.row.Sync] for cid, drone_rows in drones.items()}
    counts = {cid: len(s) for cid, s in sync_rows.items()}
    if len(set(counts.values())) > 1:
        detail = "; ".join(
            f"CID {cid} has {len(s)} (rows {_rows_text(s)})" for cid, s in sorted(sync_rows.items())
        )
        raise TaskFileError(
            f"unequal sync points: {detail}. CoUAS matches sync points by their order, so every "
            "drone needs the same number of Sync rows, or some drone would wait for ever"
        )
    steps = _couas_steps(drones)
    plans = []
    for cid in sorted(drones):
        renumbered = [a.model_copy(update={"step": s}) for a, s in zip(actions[cid], steps[cid], strict=True)]
        plans.append(AgentPlan(cid=cid, actions=renumbered))
    try:
        return TaskFile(name=name, allow_airborne_end=allow_airborne_end, plans=plans)
    except ValidationError as exc:
        raise TaskFileError(f"invalid CoUAS task file: {first_error(exc)}") from None


def first_error(exc: ValidationError) -> str:
    """The first problem pydantic found, as one line without pydantic's own prefixes."""
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ()))
    message = str(err.get("msg", "invalid"))
    cause = (err.get("ctx") or {}).get("error")
    if err.get("type") == "value_error" and cause is not None:
        message = str(cause)  # drop "Value error, "
    return f"{where}: {message}" if where else message


def parse_task_document(document: Any, *, allow_airborne_end: bool = False, gcj02: bool = False) -> TaskFile:
    """Validate a parsed JSON document of either format; raise :class:`TaskFileError` on any problem.

    ``allow_airborne_end`` is the operator's explicit consent to plans that never land; it is
    added to what the file itself says. ``gcj02`` applies to CoUAS files only.
    """
    if isinstance(document, list):
        return from_couas(document, allow_airborne_end=allow_airborne_end, gcj02=gcj02)
    not_a_task = _not_a_task(document)
    if not_a_task:
        raise TaskFileError(not_a_task)
    if allow_airborne_end and isinstance(document, dict):
        document = {**document, "allow_airborne_end": True}
    try:
        task = TaskFile.model_validate(document)
    except ValidationError as exc:
        raise TaskFileError(f"invalid task file: {first_error(exc)}") from None
    require_landing(task)
    return task


GEOJSON_TYPES = ("FeatureCollection", "Feature", "Polygon", "MultiPolygon")
SUPPORTED = (
    "a mission is a fleetgcs task file (JSON with 'plans'), a CoUAS task file (JSON array), or one "
    "QGroundControl .plan / Mission Planner .waypoints file per drone"
)


def _not_a_task(document: Any) -> str | None:
    """Why ``document`` is not a task document at all (another format), or None if it may be one."""
    if not isinstance(document, dict):
        return f"not a task file: a JSON {type(document).__name__}; {SUPPORTED}"
    if "plans" in document or document.get("format") == "fleetgcs-task":
        return None
    if document.get("fileType") == "Plan":
        return (
            "a QGroundControl .plan is one drone's mission: run it as a file (`gcs run DRONE.plan`, "
            "the file name names the drone) or POST it to /api/v1/missions/import"
        )
    if document.get("type") in GEOJSON_TYPES:
        return (
            "a GeoJSON area is not a mission: plan a search over it first "
            "(`gcs plan AREA --out plan/`, then `gcs run plan/mission.json`)"
        )
    return f"not a task file (it has no 'plans'); {SUPPORTED}"


def load_task_text(text: str, *, allow_airborne_end: bool = False, gcj02: bool = False) -> TaskFile:
    """Parse task-file JSON text of either format."""
    body = text.lstrip("\ufeff").lstrip()
    if body.startswith("<"):
        raise TaskFileError(
            "a KML (XML) document is not a mission: plan a search over its area first "
            "(`gcs plan AREA.kml --out plan/`, then `gcs run plan/mission.json`)"
        )
    try:
        document = json.loads(body)
    except json.JSONDecodeError as exc:
        raise TaskFileError(f"task file is not JSON ({SUPPORTED}): {exc}") from None
    return parse_task_document(document, allow_airborne_end=allow_airborne_end, gcj02=gcj02)
