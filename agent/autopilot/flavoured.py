"""What the pymavlink and MAVSDK backends do alike above their links, written once.

Both keep a :class:`~agent.autopilot.vehicle_state.VehicleState` and ask the vehicle's
:class:`~agent.autopilot.flavours.Flavour` what differs per firmware; this base class holds the
steps that are the same whatever carries the command: the pilot gate's questions, the PX4 leg
flown as a reposition, arming through pre-arm refusals, the return altitude and the hold.
"""

from __future__ import annotations

import abc
import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable

from agent.autopilot.base import (
    ARM_RETRY_INTERVAL_S,
    Autopilot,
    AutopilotError,
    CommandRefused,
    CommandTimeout,
)
from agent.autopilot.flavours import Flavour
from agent.autopilot.flavours.base import base_altitude_amsl
from agent.autopilot.mavlink_link import mavlink
from agent.autopilot.pilot_gate import PilotGate
from agent.autopilot.vehicle_state import VehicleState

log = logging.getLogger(__name__)

__all__ = ["FlavouredAutopilot", "positive"]

# PX4's pause from speed brakes past the point where it comes to rest and flies back to it, 0.6-1.7 m
# at up to 0.63 m/s some 3-8 s later (measured on real PX4 SITL from 3-4 m/s). The pause is sent once
# more as the vehicle's speed along its first direction falls below SETTLE_AT_MPS (so also when it
# turns back before slowing that far, wobbling sideways), and PX4 holds where it is then. Below
# SETTLE_FROM_MPS a pause stops where asked; the second one waits at most SETTLE_WITHIN_S.
SETTLE_FROM_MPS = 1.0
SETTLE_AT_MPS = 0.3
SETTLE_WITHIN_S = 10.0
SETTLE_POLL_S = 0.1


def positive(what: str, value: float) -> float:
    """``value`` when it is a positive finite number; ValueError naming ``what`` otherwise."""
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{what} must be a positive number, not {value!r}")
    return value


class FlavouredAutopilot(Autopilot):
    """An :class:`Autopilot` whose firmware conventions come from a :class:`Flavour`."""

    _state: VehicleState
    _leg_speed: float | None  # PX4: the last speed asked for, sent with each reposition
    _holds = 0  # counts pauses and legs: a settling pause that is no longer the last one is dropped
    _settling: asyncio.Task[None] | None = None

    @property
    @abc.abstractmethod
    def flavour(self) -> Flavour:
        """The vehicle's firmware conventions, from its heartbeat."""

    @abc.abstractmethod
    async def _reposition(
        self, what: str, lat: float, lon: float, alt_amsl: float, speed: float | None
    ) -> None:
        """MAV_CMD_DO_REPOSITION as COMMAND_INT (frame GLOBAL: z is AMSL), told to the pilot gate."""

    # ------------------------------------------------------------ the pilot gate

    @property
    def _pilot(self) -> PilotGate:
        return self._state.pilot

    def pilot_modes(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        flavour = self.flavour
        return flavour.failsafe_modes, flavour.release_modes

    def adopt_mode(self) -> None:
        self._state.adopt()

    def _set_leg_active(self, active: bool) -> None:
        if active:
            self._holds += 1  # a leg after a pause: its settling step must not stop the leg
        self._state.leg(self.flavour, active)

    # ------------------------------------------------------------ PX4's pause, settled

    async def _pause(self, send: Callable[[], Awaitable[None]]) -> None:
        """PX4's pause through ``send``; when the vehicle was moving fast, sent once more as it has
        slowed (:data:`SETTLE_FROM_MPS`), unless another pause, a leg or a mode change came first."""
        tel = self.telemetry()
        speed = math.hypot(tel.vn, tel.ve)
        await send()
        self._set_leg_active(False)
        self._holds += 1
        if speed >= SETTLE_FROM_MPS:
            if self._settling is not None:
                self._settling.cancel()
            heading = (tel.vn / speed, tel.ve / speed)
            self._settling = asyncio.get_running_loop().create_task(
                self._settle(self._holds, heading, send), name="pause-settle"
            )

    async def _settle(
        self, holds: int, heading: tuple[float, float], send: Callable[[], Awaitable[None]]
    ) -> None:
        """The second pause, once the speed along ``heading`` (the direction when paused) is low."""
        deadline = time.monotonic() + SETTLE_WITHIN_S
        while time.monotonic() < deadline:
            await asyncio.sleep(SETTLE_POLL_S)
            tel = self.telemetry()
            if holds != self._holds or tel.mode != "LOITER" or not tel.armed or tel.landed:
                return  # moved on: a leg, a return, a landing, the pilot or a newer pause
            if tel.vn * heading[0] + tel.ve * heading[1] < SETTLE_AT_MPS:
                try:
                    self._pilot.movable("hold")
                    await send()
                except (AutopilotError, ConnectionError) as exc:
                    log.info("pause not settled: %s", exc)
                return
        log.info("pause not settled: above %.1f m/s onward after %.0f s", SETTLE_AT_MPS, SETTLE_WITHIN_S)

    # ------------------------------------------------------------ steps both backends take

    def _mode_request(self, name: str, mav_type: int) -> tuple[tuple[float, ...], int, str]:
        """(MAV_CMD_DO_SET_MODE params, custom mode, the mode its heartbeat will show) for ``name``,
        encoded by the flavour; :class:`CommandRefused` when the flavour has no such mode."""
        flavour = self.flavour
        try:
            params, custom = flavour.mode_command(name, mav_type)
        except KeyError:
            raise CommandRefused(f"mode {name}", f"no such {flavour.name} mode") from None
        raw = flavour.decode_mode(mav_type, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom)
        return params, custom, raw

    async def _land_point(self, lat: float | None, lon: float | None) -> None:
        """Before a landing: fly to lat/lon when given (the land commands ignore a position)."""
        if (lat is None) != (lon is None):
            raise ValueError("land: give both lat and lon, or neither")
        if lat is not None and lon is not None:
            await self.approach_landing_point(lat, lon)

    async def _arm_retrying(self, deadline_s: float, attempt: Callable[[], Awaitable[None]]) -> None:
        """Run ``attempt`` (mode first where the flavour needs one, then arm) until it is accepted,
        retrying pre-arm refusals and lost answers every ARM_RETRY_INTERVAL_S until ``deadline_s``."""
        deadline = time.monotonic() + deadline_s
        last: AutopilotError | None = None
        while True:
            self.ensure_link("arm")
            try:
                await attempt()
                return
            except (CommandRefused, CommandTimeout) as exc:
                last = exc
                log.info("arm attempt failed: %s", exc)
            if time.monotonic() + ARM_RETRY_INTERVAL_S >= deadline:
                break
            await asyncio.sleep(ARM_RETRY_INTERVAL_S)
        if isinstance(last, CommandRefused):
            raise CommandRefused("arm", last.reason)
        raise CommandTimeout("arm", deadline_s)

    async def _reposition_leg(
        self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None
    ) -> None:
        """PX4's goto: DO_REPOSITION with the speed in param1 (the last one asked for when none)."""
        if speed_mps is not None:
            self._leg_speed = speed_mps
        alt_amsl = base_altitude_amsl(self.telemetry()) + alt_rel_m
        await self._reposition("goto", lat, lon, alt_amsl, self._leg_speed)
        self._set_leg_active(True)

    def _return_alt(self, alt_rel_m: float | None) -> float | None:
        """The return altitude to set: the one asked for, or the flavour's default (None: the vehicle's)."""
        if alt_rel_m is None:
            return self.flavour.default_return_alt(self.telemetry())
        return positive("return altitude", alt_rel_m)

    async def _hold_in_modes(self, set_mode: Callable[[str], Awaitable[None]]) -> None:
        """Hold by switching mode: the flavour's hold modes in turn, the next when one is refused."""
        modes = self.flavour.hold_modes
        for i, mode in enumerate(modes):
            try:
                await set_mode(mode)
                return
            except CommandRefused as exc:
                if i + 1 == len(modes):
                    raise
                log.info("%s refused (%s); trying %s", mode, exc.reason, modes[i + 1])

    async def _fence_parameters(self, params: list[tuple[str, float]]) -> bool:
        """Write the flavour's fence parameters in order, after its items; False (logged) when the
        vehicle does not take one (the agent then keeps enforcing the fence itself)."""
        try:
            for name, value in params:
                await self.set_param(name, value)
        except (CommandRefused, CommandTimeout) as exc:
            log.warning("fence parameters not accepted: %s", exc)
            return False
        return True

    @abc.abstractmethod
    async def set_param(self, name: str, value: float) -> object:
        """Write one autopilot parameter (the flavour says how integers travel)."""

    def _pause_now(self) -> tuple[float, ...] | None:
        """The flavour's pause (PX4) when the vehicle is flying; None: hold by mode."""
        pause = self.flavour.pause_params()
        tel = self.telemetry()
        return pause if pause is not None and tel.armed and not tel.landed else None
