"""Shared pieces of the fault-injection tests: recording what each agent was released, mission shapes."""

from __future__ import annotations

from agent.config import AgentSettings
from gcs.core.daemon import Daemon
from protocol.actions import Action, Goto, Hold, Land, Takeoff
from protocol.geo import offset_latlon
from protocol.taskfile import AgentPlan, TaskFile
from tests.backbone.helpers import HOME, RunningAgent


def record_releases(running: RunningAgent) -> list[int]:
    """Every release step the agent's queue receives, in arrival order (repeats included).

    Wraps the queue's ``release`` on the instance, so the agent is observed, not changed.
    """
    seen: list[int] = []
    queue = running.agent.queue
    original = queue.release

    def release(mission_id: str, step: int) -> None:
        seen.append(step)
        original(mission_id, step)

    queue.release = release  # type: ignore[method-assign]
    return seen


def first_occurrences(steps: list[int]) -> list[int]:
    """``steps`` with repeats removed, first occurrence kept (a re-sent release is harmless)."""
    out: list[int] = []
    for step in steps:
        if step not in out:
            out.append(step)
    return out


def released_steps(daemon: Daemon, mission_id: str) -> list[int]:
    """Steps of ``mission_id`` in the order the daemon released them (one event per release)."""
    return [
        int(e.data["step"])
        for e in daemon.events.history(kind="sync_released", limit=10_000)
        if e.mission_id == mission_id
    ]


def failsafe_settings(timeout_s: float, action: str = "rtl") -> AgentSettings:
    """Agent settings with a lost-link failsafe, status at 10 Hz like the test daemon."""
    return AgentSettings(
        status_period_s=0.1,
        acceptance_radius_m=1.0,
        lost_link_timeout_s=timeout_s,
        lost_link_action=action,  # type: ignore[arg-type]
    )


def quiet_mission(identities: list[str], hold_s: float, name: str = "quiet") -> TaskFile:
    """Takeoff, a short leg, a long hold (all sync), land: the daemon says nothing during the hold."""
    plans = []
    for index, identity in enumerate(identities):
        lat, lon = offset_latlon(HOME[0], HOME[1], 10.0, 6.0 * index)
        actions: list[Action] = [
            Takeoff(step=0, alt=5.0, sync=True),
            Goto(step=1, lat=lat, lon=lon, alt=5.0, sync=True),
            Hold(step=2, seconds=hold_s, sync=True),
            Land(step=3),
        ]
        plans.append(AgentPlan(agent=identity, actions=list(actions)))
    return TaskFile(name=name, plans=plans)


def hover_mission(identity: str, seconds: float = 60.0, north_m: float = 10.0) -> TaskFile:
    """Take off, fly ``north_m`` out and hover: a vehicle away from home, for failsafe tests."""
    lat, lon = offset_latlon(HOME[0], HOME[1], north_m, 0.0)
    actions: list[Action] = [
        Takeoff(step=0, alt=5.0),
        Goto(step=1, lat=lat, lon=lon, alt=5.0),
        Hold(step=2, seconds=seconds),
    ]
    return TaskFile(name="hover", plans=[AgentPlan(agent=identity, actions=list(actions))])
