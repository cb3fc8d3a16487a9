"""The pymavlink backend's telemetry streams: asked for at connect, re-asserted while connected.

SET_MESSAGE_INTERVAL per message, REQUEST_DATA_STREAM when the vehicle does not take it; an
interval the vehicle refused (PX4: MISSION_CURRENT, streamed anyway) is never re-asserted. The
reader thread's tick re-sends the intervals of streams gone stale and all of them every
:data:`STREAM_FULL_REASSERT_S` (a rebooted or reconfigured vehicle reverts them), and asks for
HOME_POSITION until one arrives. Rates and rules: ``docs/autopilot-backends.md``.
"""

from __future__ import annotations

import logging
import time

from agent.autopilot.base import CommandRefused, CommandTimeout
from agent.autopilot.mavlink_link import MavlinkLink, mavlink
from agent.autopilot.vehicle_state import VehicleState

log = logging.getLogger(__name__)

__all__ = ["STREAMS", "StreamKeeper"]

# Messages we ask the vehicle to stream: (name, id, rate) where rate None means telemetry_hz.
_FAST = None
STREAMS: tuple[tuple[str, int, float | None], ...] = (
    ("GLOBAL_POSITION_INT", mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, _FAST),
    ("ATTITUDE", mavlink.MAVLINK_MSG_ID_ATTITUDE, _FAST),
    ("VFR_HUD", mavlink.MAVLINK_MSG_ID_VFR_HUD, _FAST),
    ("EXTENDED_SYS_STATE", mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, _FAST),
    ("MISSION_CURRENT", mavlink.MAVLINK_MSG_ID_MISSION_CURRENT, _FAST),
    ("GPS_RAW_INT", mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 2.0),
    ("SYS_STATUS", mavlink.MAVLINK_MSG_ID_SYS_STATUS, 2.0),
    ("BATTERY_STATUS", mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, 2.0),
    ("HOME_POSITION", mavlink.MAVLINK_MSG_ID_HOME_POSITION, 0.5),
)
STREAM_FULL_REASSERT_S = 30.0
STREAM_STALE_REASSERT_MIN_S = 3.0


class StreamKeeper:
    """Asks for the telemetry streams and keeps them flowing (ticks on the link's reader thread)."""

    def __init__(self, link: MavlinkLink, state: VehicleState, telemetry_hz: float) -> None:
        self._link = link
        self._state = state
        self.telemetry_hz = telemetry_hz
        self._ready = False
        self._requested_at: dict[str, float] = {}
        self._refused: set[str] = set()  # SET_MESSAGE_INTERVAL refused: never re-asserted
        self._last_full_reassert = 0.0
        self._last_home_request = 0.0

    def plan(self) -> list[tuple[str, int, float]]:
        return [(name, mid, self.telemetry_hz if hz is None else hz) for name, mid, hz in STREAMS]

    async def setup(self) -> None:
        """SET_MESSAGE_INTERVAL per message; REQUEST_DATA_STREAM when the vehicle does not take it."""
        refused = 0
        fallback = False
        for name, msg_id, hz in self.plan():
            try:
                await self._link.command(
                    f"stream {name}",
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    (msg_id, 1e6 / hz),
                    retries=2,
                )
                self._requested_at[name] = time.monotonic()
            except CommandRefused as exc:
                # PX4 refuses MISSION_CURRENT (it streams it anyway): not re-asserted, no fallback
                # while other intervals are taken.
                log.debug("SET_MESSAGE_INTERVAL %s refused (%s)", name, exc.reason)
                self._refused.add(name)
                refused += 1
            except CommandTimeout:
                log.info("SET_MESSAGE_INTERVAL unanswered; falling back to REQUEST_DATA_STREAM")
                fallback = True
                break
        if fallback or (refused and refused == len(self.plan())):
            self._request_data_streams()
        self._last_full_reassert = time.monotonic()
        self._ready = True
        self._request_home()
        try:
            await self._link.command(
                "request AUTOPILOT_VERSION",
                mavlink.MAV_CMD_REQUEST_MESSAGE,
                (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,),
                retries=1,
            )
        except (CommandRefused, CommandTimeout):
            log.info("vehicle does not answer AUTOPILOT_VERSION requests")

    def _request_data_streams(self) -> None:
        rate = max(1, round(self.telemetry_hz))
        self._link.send(
            mavlink.MAVLink_request_data_stream_message(
                self._link.target_system, self._link.target_component, mavlink.MAV_DATA_STREAM_ALL, rate, 1
            )
        )

    def _request_home(self) -> None:
        self._last_home_request = time.monotonic()
        self._link.send_command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, (mavlink.MAVLINK_MSG_ID_HOME_POSITION,))

    def _reassert(self, only_stale: bool) -> None:
        """Re-send interval requests, fire-and-forget (the vehicle may have reverted them)."""
        now = time.monotonic()
        for name, msg_id, hz in self.plan():
            if name in self._refused:
                continue
            if only_stale:
                last = self._link.last_seen.get(name, 0.0)
                stale_after = max(3.0 / hz, 2.0)
                if now - last < stale_after:
                    continue
                if now - self._requested_at.get(name, 0.0) < STREAM_STALE_REASSERT_MIN_S:
                    continue
            self._requested_at[name] = now
            self._link.send_command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / hz))

    def on_tick(self) -> None:  # reader thread, every 0.5 s
        if not self._ready or not self._link.link_ok():
            return
        now = time.monotonic()
        if now - self._last_full_reassert > STREAM_FULL_REASSERT_S:
            self._last_full_reassert = now
            self._reassert(only_stale=False)
        else:
            self._reassert(only_stale=True)
        if self._state.tel.home_lat is None and now - self._last_home_request > 2.0:
            self._request_home()

    def on_link_restored(self) -> None:  # reader thread
        if self._ready:
            self._last_full_reassert = time.monotonic()
            self._reassert(only_stale=False)
            self._request_home()
