"""Run one protocol action on an autopilot until it is complete, or fail with a reason.

Completion is judged from telemetry, the same way for every backend: arrival within the
acceptance radius (horizontal) and 1 m (vertical), takeoff at ``takeoff_tolerance`` of the
target altitude (a take-off the autopilot ends short of it is climbed the rest as a target),
landing when the vehicle reports landed and disarmed. Position targets are re-sent every
``resend_target_s`` while the vehicle gets no closer to them (ArduPilot does not acknowledge
them; PX4 may drop one at the end of a take-off), never while it flies to them.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time

from agent.autopilot.base import Autopilot, AutopilotError, PilotInControl
from agent.config import AgentConfig
from protocol.actions import (
    Action,
    GoBy,
    Goto,
    Hold,
    Land,
    ReturnToLaunch,
    SetSpeed,
    Takeoff,
    Waypoints,
)
from protocol.geo import distance_m, offset_latlon
from protocol.packets import ActionFailure

log = logging.getLogger(__name__)

POLL_S = 0.05
# Closer to the target by this much over a re-send period: the vehicle flies to it, no re-send.
RESEND_PROGRESS_M = 1.0
VERTICAL_TOLERANCE_M = 1.0
ARM_REPORT_GRACE_S = 5.0
# A take-off that gains less than TAKEOFF_PROGRESS_M in TAKEOFF_STALL_S of vehicle time, past half its
# height, has ended short of it (the autopilot holds where its own take-off ended).
TAKEOFF_PROGRESS_M = 0.2
TAKEOFF_STALL_S = 4.0


class ActionFailed(Exception):
    """The action could not be completed; the message says why (shown to the operator)."""


def default_timeout(action: Action) -> float:
    """A generous per-action time limit when the action does not set one."""
    if action.timeout_s is not None:
        return action.timeout_s
    if isinstance(action, Takeoff):
        return 90.0 + action.alt / 0.5
    if isinstance(action, Hold):
        return action.seconds + 10.0
    if isinstance(action, (Land, ReturnToLaunch)):
        return 600.0
    if isinstance(action, SetSpeed):
        return 10.0
    return 3600.0  # legs: bounded by battery long before this


class VehicleClock:
    """Seconds elapsed on the vehicle's clock since this object was made.

    Why: a ``hold`` of N seconds is N seconds of the vehicle's time. On a real autopilot that is
    wall time; in a simulator running N times faster it is not, and a hold timed on the wall
    clock would last N times too long in flight. The autopilot's clock (``time_boot_ms``, as
    ``Telemetry.vehicle_time_s``) is used when it reports one; a jump back (the autopilot
    rebooted) counts as no time, and without a vehicle clock the wall clock is used.
    """

    def __init__(self, autopilot: Autopilot) -> None:
        self._autopilot = autopilot
        self._last = autopilot.telemetry().vehicle_time_s
        self._wall = time.monotonic()
        self._elapsed = 0.0

    def elapsed(self) -> float:
        now = self._autopilot.telemetry().vehicle_time_s
        if self._last is None or now is None:
            wall = time.monotonic()
            self._elapsed += wall - self._wall
            self._wall, self._last = wall, now
            return self._elapsed
        if now > self._last:
            self._elapsed += now - self._last
        self._last, self._wall = now, time.monotonic()
        return self._elapsed


class ActionExecutor:
    """Executes actions on one autopilot with the agent's settings."""

    def __init__(self, autopilot: Autopilot, config: AgentConfig) -> None:
        self.autopilot = autopilot
        self.config = config
        self.cruise_mps: float | None = None
        # What is left of the running action if it is interrupted now (pause), or None when idle.
        self.continuation: Action | None = None
        # The last failed action, reported in every status until another action starts.
        self.failure: ActionFailure | None = None
        # Where the plan so far leaves the vehicle (lat, lon, alt above home): the target of the
        # last takeoff/goto/go_by/waypoints. A go_by is an offset from here, not from wherever
        # the vehicle happened to be when the previous leg was judged reached (up to the
        # acceptance radius short of it): a chain of go_by legs keeps its shape instead of
        # drifting by a radius per leg. None at first and after a landing, an rtl, a failure
        # or new orders (:meth:`forget_anchor`): the go_by is taken from the vehicle's position.
        self.anchor: tuple[float, float, float] | None = None

    def forget_anchor(self) -> None:
        """The queue was replaced or emptied: the next go_by starts from where the vehicle is."""
        self.anchor = None

    async def run(self, action: Action) -> None:
        """Execute ``action`` to completion within its timeout, else raise :class:`ActionFailed`.

        The failure is also kept in :attr:`failure` (step, kind, the autopilot's reason) for the
        status reports, so the daemon's mission runner can apply its policy.
        """
        limit = default_timeout(action)
        self.continuation = action
        self.failure = None
        try:
            try:
                async with asyncio.timeout(limit):
                    await self._await_position(action)
                    try:
                        await self._dispatch(action)
                    except PilotInControl:
                        # A pilot took the vehicle: not a failure of the action. The monitor empties
                        # the queue (cancelling this) at its next check; the timeout bounds the wait.
                        await asyncio.Event().wait()
            except TimeoutError:
                raise ActionFailed(f"did not complete within {limit:.0f} s") from None
            except AutopilotError as exc:
                raise ActionFailed(str(exc)) from None
        except ActionFailed as exc:
            self.anchor = None
            self.failure = ActionFailure(
                step=action.step, kind=action.kind, reason=str(exc)[:300], time=time.time()
            )
            raise ActionFailed(f"{action.kind} (step {action.step}): {exc}") from None
        self.continuation = None

    async def _await_position(self, action: Action) -> None:
        """No action can be planned from an unknown position (ArduCopter: lat/lon 0,0 at boot).

        A takeoff waits for the first 3-D fix up to the arm deadline (arming would be refused
        until then anyway); any other action fails at once.
        """
        ap = self.autopilot
        if ap.telemetry().position_known:
            return
        if isinstance(action, Takeoff):
            deadline = time.monotonic() + self.config.arm_deadline_s
            while time.monotonic() < deadline:
                if ap.telemetry().position_known:
                    return
                await asyncio.sleep(POLL_S * 4)
        t = ap.telemetry()
        raise ActionFailed(
            f"no position: the vehicle has not reported a 3-D GPS fix (fix type {t.gps_fix}, "
            f"{t.satellites} satellites)"
        )

    async def _dispatch(self, action: Action) -> None:
        ap = self.autopilot
        if isinstance(action, Takeoff):
            now = ap.telemetry()
            self.anchor = (now.lat, now.lon, action.alt)
            await self._takeoff(action.alt)
        elif isinstance(action, Goto):
            self.anchor = (action.lat, action.lon, action.alt)
            await self._fly_to(action.lat, action.lon, action.alt, action.speed)
        elif isinstance(action, GoBy):
            await self._go_by(action)
        elif isinstance(action, Waypoints):
            for index, point in enumerate(action.points):
                self.continuation = action.model_copy(update={"points": action.points[index:]})
                self.anchor = (point.lat, point.lon, point.alt)
                await self._fly_to(point.lat, point.lon, point.alt, action.speed)
        elif isinstance(action, Land):
            self.anchor = None
            now = ap.telemetry()
            if now.landed and not now.armed:
                return  # already down (a stand-down sent to a drone that had not taken off)
            await ap.land(action.lat, action.lon)
            await self._until_disarmed()
        elif isinstance(action, ReturnToLaunch):
            self.anchor = None
            await ap.return_to_launch(action.alt)
            await self._until_disarmed()
        elif isinstance(action, Hold):
            await ap.hold()
            clock = VehicleClock(ap)
            while (left := action.seconds - clock.elapsed()) > 0:
                self.continuation = action.model_copy(update={"seconds": left})
                await asyncio.sleep(min(left, POLL_S * 4))
        elif isinstance(action, SetSpeed):
            await ap.set_speed(action.speed)
            self.cruise_mps = action.speed
        else:  # pragma: no cover - the Action union is exhaustive
            raise ActionFailed(f"unknown action {action!r}")

    def go_by_target(self, action: GoBy) -> tuple[float, float, float]:
        """Where ``action`` ends: its offset from :attr:`anchor`, else from the vehicle's position."""
        if self.anchor is not None:
            base = self.anchor
        else:
            now = self.autopilot.telemetry()
            base = (now.lat, now.lon, now.alt_rel)
        lat, lon = offset_latlon(base[0], base[1], action.north, action.east)
        return (lat, lon, base[2] + action.up)

    async def _go_by(self, action: GoBy) -> None:
        """Fly a go_by: anchored (the plan's last target + offset) as a goto, else as a local offset."""
        ap = self.autopilot
        anchored = self.anchor is not None
        lat, lon, alt = self.go_by_target(action)
        # If interrupted, what is left is a plain goto to the same fixed target.
        self.continuation = action.as_goto(lat, lon, alt)
        self.anchor = (lat, lon, alt)
        if anchored:
            await self._fly_to(lat, lon, alt, action.speed)
        else:
            await ap.go_by(action.north, action.east, action.up, action.speed)
            await self._fly_to(lat, lon, alt, action.speed, already_sent=True)

    async def _takeoff(self, alt: float) -> None:
        ap = self.autopilot
        now = ap.telemetry()
        if not now.landed and now.armed:
            # Already airborne (e.g. a resumed plan): a takeoff means "climb to alt".
            await self._fly_to(now.lat, now.lon, alt, None)
            return
        await ap.arm(self.config.arm_deadline_s)
        # The autopilot has accepted arming; its heartbeat may take a moment to say so.
        seen_armed = time.monotonic() + ARM_REPORT_GRACE_S
        while not ap.telemetry().armed:
            if time.monotonic() > seen_armed:
                raise ActionFailed(
                    f"the vehicle accepted arming but did not report armed in {ARM_REPORT_GRACE_S:.0f} s"
                )
            await asyncio.sleep(POLL_S)
        await ap.takeoff(alt)
        target = alt * self.config.takeoff_tolerance
        best, since = ap.telemetry().alt_rel, VehicleClock(ap)
        while (now := ap.telemetry()).alt_rel < target:
            if not now.armed:
                raise ActionFailed("the vehicle disarmed during takeoff")
            if now.alt_rel > best + TAKEOFF_PROGRESS_M:
                best, since = now.alt_rel, VehicleClock(ap)
            elif now.alt_rel >= alt / 2 and since.elapsed() >= TAKEOFF_STALL_S:
                # The autopilot ended its take-off short: PX4 climbs to an AMSL altitude, and its
                # height above the home it re-takes at arming came out 0.7 m short of 8 m under load
                # (real PX4 SITL, tests/px4). Climb the rest as a target instead of waiting forever.
                log.info("take-off stopped at %.1f m of %.1f m: climbing the rest", now.alt_rel, alt)
                await self._fly_to(now.lat, now.lon, alt, None)
                return
            await asyncio.sleep(POLL_S)

    async def _fly_to(
        self, lat: float, lon: float, alt: float, speed: float | None, *, already_sent: bool = False
    ) -> None:
        ap = self.autopilot
        speed = speed or self.cruise_mps
        if not already_sent:
            await ap.goto(lat, lon, alt, speed)
        sent_at = time.monotonic()
        radius = self.config.settings.acceptance_radius_m
        gap_then: float | None = None  # distance to the target when the re-send period began
        while True:
            now = ap.telemetry()
            if not now.armed:
                raise ActionFailed("the vehicle is no longer armed")
            horizontal = distance_m(now.lat, now.lon, lat, lon)
            if horizontal <= radius and abs(now.alt_rel - alt) <= max(VERTICAL_TOLERANCE_M, radius / 2):
                return
            gap = math.hypot(horizontal, now.alt_rel - alt)
            if gap_then is None:
                gap_then = gap
            if time.monotonic() - sent_at >= self.config.resend_target_s:
                # Re-send only a target the vehicle is not flying to (lost, or dropped at the end of a
                # take-off): on PX4 every DO_REPOSITION is a switch to Hold, and one sent before the
                # agent hears a pilot's new mode (1 heartbeat a second) would take the vehicle back.
                if gap > gap_then - RESEND_PROGRESS_M:
                    await ap.goto(lat, lon, alt, None)
                sent_at, gap_then = time.monotonic(), gap
            await asyncio.sleep(POLL_S)

    async def hold_vehicle(self) -> None:
        """Brake and hold position if flying (used by pause and by failures)."""
        now = self.autopilot.telemetry()
        if now.armed and not now.landed:
            await self.autopilot.hold()

    async def _until_disarmed(self) -> None:
        ap = self.autopilot
        while True:
            now = ap.telemetry()
            if now.landed and not now.armed:
                return
            await asyncio.sleep(POLL_S)
