"""The mission task file: per-agent ordered actions with sync points (JSON, pydantic schema).

Two formats are read:

* the fleetgcs task file (:class:`TaskFile`, ``"format": "fleetgcs-task"``), documented in
  ``docs/protocol.md``;
* the original CoUAS task file: a JSON array of objects with ``Action_type`` (0 arm-and-takeoff
  ``Alt``; 1 go-to ``Lat``/``Lon``/``Alt``; 2 go-by ``N``/``E``/``Alt``; 3 land ``Lat``/``Lon``
  with 0,0 meaning "here"), ``CID``, ``Step``, ``Sync`` and optional ``Time``.

Validation makes the barrier service safe by construction: every agent's plan starts with a
takeoff, steps never go backwards, and every agent has the same sequence of sync steps, so no
barrier can wait on an agent that will never reach it.
"""

from __future__ import annotations

import json
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from protocol.actions import Action, GoBy, Goto, Land, Takeoff


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
    plans: list[AgentPlan] = Field(min_length=1, max_length=1000)

    @model_validator(mode="after")
    def _flyable(self) -> TaskFile:
        validate_plans(self.plans)
        return self


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

    Action_type: Literal[0, 1, 2, 3]
    CID: int = Field(ge=1, le=65_535)
    Step: int = Field(ge=0)
    Sync: int | bool = 0
    Time: float | None = None
    Alt: float | None = None
    Lat: float | None = None
    Lon: float | None = None
    N: float | None = None
    E: float | None = None


def _couas_action(row: _CouasRow, index: int) -> Any:
    step, sync = row.Step, bool(row.Sync)

    def need(name: str, value: float | None) -> float:
        if value is None:
            raise TaskFileError(f"CoUAS row {index} (Action_type {row.Action_type}) lacks '{name}'")
        return value

    if row.Action_type == 0:
        return Takeoff(alt=need("Alt", row.Alt), step=step, sync=sync)
    if row.Action_type == 1:
        return Goto(
            lat=need("Lat", row.Lat), lon=need("Lon", row.Lon), alt=need("Alt", row.Alt), step=step, sync=sync
        )
    if row.Action_type == 2:
        return GoBy(north=need("N", row.N), east=need("E", row.E), up=row.Alt or 0.0, step=step, sync=sync)
    lat, lon = row.Lat or 0.0, row.Lon or 0.0
    if lat == 0.0 and lon == 0.0:
        return Land(step=step, sync=sync)
    return Land(lat=lat, lon=lon, step=step, sync=sync)


def from_couas(rows: list[Any], name: str = "couas-mission") -> TaskFile:
    """Convert an original CoUAS task file (already parsed JSON) into a :class:`TaskFile`."""
    if not isinstance(rows, list) or not rows:
        raise TaskFileError("a CoUAS task file is a non-empty JSON array of action objects")
    by_cid: dict[int, list[Any]] = {}
    for index, raw in enumerate(rows):
        try:
            row = _CouasRow.model_validate(raw)
            action = _couas_action(row, index)
        except ValidationError as exc:
            raise TaskFileError(f"CoUAS row {index}: {_first_error(exc)}") from None
        by_cid.setdefault(row.CID, []).append((row.Step, index, action))
    plans = []
    for cid, entries in sorted(by_cid.items()):
        entries.sort(key=lambda e: (e[0], e[1]))  # by step, then file order
        plans.append(AgentPlan(cid=cid, actions=[e[2] for e in entries]))
    return parse_task_document({"name": name, "plans": [p.model_dump() for p in plans]})


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ()))
    return f"{where}: {err.get('msg', 'invalid')}" if where else str(err.get("msg", "invalid"))


def parse_task_document(document: Any) -> TaskFile:
    """Validate a parsed JSON document of either format; raise :class:`TaskFileError` on any problem."""
    if isinstance(document, list):
        return from_couas(document)
    try:
        return TaskFile.model_validate(document)
    except ValidationError as exc:
        raise TaskFileError(f"invalid task file: {_first_error(exc)}") from None


def load_task_text(text: str) -> TaskFile:
    """Parse task-file JSON text of either format."""
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TaskFileError(f"task file is not JSON: {exc}") from None
    return parse_task_document(document)
