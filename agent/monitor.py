"""Exception monitor: watches the vehicle and the daemon link and acts on the autopilot itself.

Each exception fires its reaction once when it starts (edge-triggered) and stays listed in
the status report while it lasts, so a flapping condition cannot spam the autopilot and the
daemon always sees what is active. Reactions that move the vehicle (rtl, land, hold) first
empty the command queue, so stale commands cannot fly it back into trouble. While a pilot has
the vehicle (agent/pilot.py) every reaction only reports: the pilot has the last word.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from agent.autopilot.base import HEARTBEAT_TIMEOUT_S, Autopilot, AutopilotError, Telemetry
from agent.config import AgentSettings
from agent.pilot import MODE_REACTIONS, PilotWatch, failsafe_name, landing_without_position
from protocol.packets import Geofence

log = logging.getLogger("agent.monitor")


@dataclass(frozen=True, slots=True)
class Condition:
    name: str
    reaction: str  # report | rtl | land | hold | continue
    detail: str
    vehicle: bool = False  # the autopilot's own failsafe (it chose the mode), not the agent's reaction


def fence_violation(t: Telemetry, fence: Geofence | None) -> str | None:
    """Why the vehicle is outside ``fence``, or None when inside (or no fence/position)."""
    if fence is None or t.gps_fix < 3:
        return None
    return fence.violation(t.lat, t.lon, t.alt_rel)


class ExceptionMonitor:
    def __init__(
        self,
        autopilot: Autopilot,
        settings: AgentSettings,
        last_daemon_contact: Callable[[], float],
        interrupt_queue: Callable[[], Awaitable[None]],
        report: Callable[[str, str], Awaitable[None]],
    ) -> None:
        self._autopilot = autopilot
        self._settings = settings
        self._last_daemon_contact = last_daemon_contact
        self._interrupt_queue = interrupt_queue
        self._report = report
        self.geofence: Geofence | None = None
        self.active: dict[str, Condition] = {}
        self.failsafe: Condition | None = None  # latched vehicle-moving reaction (see latch_failsafe)
        self.pilot = PilotWatch(autopilot)

    def failsafe_text(self) -> str | None:
        return f"{self.failsafe.name}: {self.failsafe.reaction}" if self.failsafe else None

    def clear_failsafe(self) -> None:
        """An operator command takes the vehicle over from the agent's own failsafe."""
        self.failsafe = None

    def conditions(self, t: Telemetry, now: float) -> list[Condition]:
        """Every exception that holds right now (pure function of state)."""
        s = self._settings
        found: list[Condition] = []
        if t.battery_pct is not None and t.armed:
            if t.battery_pct <= s.battery_critical_pct:
                found.append(
                    Condition("battery_critical", s.battery_critical_action, f"{t.battery_pct:.0f}%")
                )
            elif t.battery_pct <= s.battery_low_pct:
                found.append(Condition("battery_low", s.battery_low_action, f"{t.battery_pct:.0f}%"))
        if t.armed and not t.landed:
            why = fence_violation(t, self.geofence)
            if why is not None:
                assert self.geofence is not None
                found.append(Condition("fence_breach", self.geofence.breach_action, why))
        last_contact = self._last_daemon_contact()
        # Timed from the last packet whether or not TCP looks up: the daemon sends at least a
        # keepalive every second, so silence means a partition even on an open connection.
        if now - last_contact > s.lost_link_timeout_s:
            found.append(
                Condition(
                    "link_lost", s.lost_link_action, f"no daemon contact for {now - last_contact:.0f} s"
                )
            )
        if t.last_heartbeat_monotonic and now - t.last_heartbeat_monotonic > HEARTBEAT_TIMEOUT_S:
            found.append(Condition("autopilot_link_lost", "report", "no autopilot heartbeat"))
        if t.armed and t.gps_fix < 3:
            found.append(Condition("gps_lost", "report", f"fix type {t.gps_fix}"))
        return found

    async def check(self) -> None:
        now = time.monotonic()
        telemetry = self._autopilot.telemetry()
        if self.failsafe is not None and telemetry.landed and not telemetry.armed:
            await self._report("failsafe_ended", f"{self.failsafe.name}: vehicle landed")
            self.failsafe = None
        current = {c.name: c for c in self.conditions(telemetry, now)}
        await self._follow_pilot(telemetry, set(current))
        if (
            self.failsafe is None
            and not self.pilot.active
            and landing_without_position(telemetry, set(current))
        ):
            self.failsafe = Condition(
                "gnss", "land", "the vehicle's own failsafe while landing", vehicle=True
            )
            await self._report(
                "vehicle_failsafe_mode", "the vehicle's own failsafe (gnss) while landing: mode LAND"
            )
        for name, condition in current.items():
            if name not in self.active:
                await self._react(condition)
        for name in set(self.active) - set(current):
            await self._report(f"{name}_cleared", "")
        self.active = current

    async def _follow_pilot(self, telemetry: Telemetry, conditions: set[str]) -> None:
        """A pilot takes the vehicle (nothing more is sent to move it), flies on, or hands back."""
        change = self.pilot.update(telemetry, conditions)
        if change is None:
            return
        mode = telemetry.pilot_mode or telemetry.mode
        if change == "took":
            log.warning("pilot in control: mode %s set by someone else; the agent stops commanding", mode)
            self.failsafe = None  # the pilot outranks the agent's own failsafe too
            await self._interrupt_queue()
            await self._report("pilot", f"pilot in control: mode {mode}; queue emptied, nothing sent")
        elif change == "changed":
            await self._report("pilot", f"pilot in control: mode {mode}")
        elif change == "handed_back":
            log.warning("pilot handed back: vehicle in %s again", telemetry.mode)
            await self._report("pilot_handback", f"vehicle in {telemetry.mode} again; the agent commands it")
        else:
            # Latched like the agent's own failsafe: the queue is emptied (nothing the agent had
            # queued may fly it out of its failsafe), lower-priority orders are refused and the
            # daemon sees StatusReport.failsafe (e.g. "gnss: land") and goes on without it.
            name = failsafe_name(telemetry, conditions)
            reaction = MODE_REACTIONS.get(mode, "hold")
            log.warning("the vehicle's own failsafe (%s): mode %s", name, mode)
            self.failsafe = Condition(
                name, reaction, f"the vehicle's own failsafe: mode {mode}", vehicle=True
            )
            await self._interrupt_queue()
            await self._report("vehicle_failsafe_mode", f"the vehicle's own failsafe ({name}): mode {mode}")

    async def _react(self, condition: Condition) -> None:
        log.warning("exception %s (%s): reaction %s", condition.name, condition.detail, condition.reaction)
        if self.pilot.active and condition.reaction not in ("report", "continue"):
            detail = f"{condition.detail}; reaction {condition.reaction} withheld: pilot in control"
            await self._report(condition.name, detail)
            return
        if (
            self.failsafe is not None
            and self.failsafe.vehicle
            and condition.reaction not in ("report", "continue")
        ):
            # The autopilot flies its own failsafe (e.g. a GNSS landing): an agent reaction would
            # fight it (an RTL without position is refused anyway); only the operator overrides.
            detail = f"{condition.detail}; reaction {condition.reaction} withheld: the vehicle's own failsafe"
            await self._report(condition.name, detail)
            return
        await self._report(condition.name, f"{condition.detail}; reaction {condition.reaction}")
        if condition.reaction in ("report", "continue"):
            return
        t = self._autopilot.telemetry()
        if t.landed or not t.armed:
            return
        # Latched until the vehicle is down or the operator takes over: a daemon pause, resume or
        # new plan of lower priority must not undo the agent's own failsafe (docs/cooperation.md).
        self.failsafe = condition
        await self._interrupt_queue()
        try:
            if condition.reaction == "rtl":
                await self._autopilot.return_to_launch()
            elif condition.reaction == "land":
                await self._autopilot.land()
            elif condition.reaction == "hold":
                await self._autopilot.hold()
        except AutopilotError as exc:
            await self._report(f"{condition.name}_reaction_failed", str(exc))

    async def run(self, period_s: float) -> None:
        while True:
            try:
                await self.check()
            except AutopilotError as exc:  # keep monitoring whatever the autopilot does
                log.error("monitor: %s", exc)
            await asyncio.sleep(period_s)


def finite_or_zero(value: float) -> float:
    return value if math.isfinite(value) else 0.0
