"""Private: the MAVLink mission upload protocol (missions, fences, rally points), and the items
the pymavlink backend uploads.

Upload sequence (https://mavlink.io/en/services/mission.html)::

    GCS → MISSION_COUNT(count, mission_type)
    vehicle → MISSION_REQUEST_INT(seq) or legacy MISSION_REQUEST(seq)   (ArduPilot still sends both)
    GCS → MISSION_ITEM_INT(seq)          (always the _INT item, as the spec asks for both requests)
    ... until vehicle → MISSION_ACK(type)

Rules that real autopilots need:

* the vehicle may request any seq, again and out of order; we answer every request;
* a MISSION_ACK with MAV_MISSION_INVALID_SEQUENCE is a NACK of one item, *not* the end of the upload
  (ArduPilot sends it for a duplicate or early item and keeps going) - we keep answering requests
  until the final MISSION_ACK;
* other error ACKs end the upload with that result;
* silence for ``item_timeout_s``: resend MISSION_COUNT (nothing requested yet) or the last item,
  at most ``retries`` times in a row, then :class:`CommandTimeout`;
* the final MISSION_ACK lost (a lossy radio): the vehicle stored the items and ended the transfer,
  so our re-sent last item gets silence (ArduPilot) or an error ACK. Once the last item was sent
  again, silence or an error other than INVALID_SEQUENCE is checked against the vehicle: when it
  reports our count and our last item (a short download), the upload went through.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

from agent.autopilot.base import CommandTimeout, FenceSpec, MissionPoint, Telemetry
from agent.autopilot.mavlink_link import MavlinkLink, Subscription, mavlink

log = logging.getLogger(__name__)


@dataclass(slots=True, frozen=True)
class Item:
    """One mission item, lat/lon in degrees (sent x1e7)."""

    command: int
    frame: int
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    autocontinue: int = 1

    def to_message(self, link: MavlinkLink, seq: int, mission_type: int) -> Any:
        for value in (self.lat, self.lon, self.alt, self.param1, self.param2, self.param3, self.param4):
            if not math.isfinite(value):
                raise ValueError(f"mission item {seq}: non-finite value")
        return mavlink.MAVLink_mission_item_int_message(
            link.target_system,
            link.target_component,
            seq,
            self.frame,
            self.command,
            0,
            self.autocontinue,
            self.param1,
            self.param2,
            self.param3,
            self.param4,
            round(self.lat * 1e7),
            round(self.lon * 1e7),
            self.alt,
            mission_type,
        )


async def upload(
    link: MavlinkLink,
    items: list[Item],
    mission_type: int,
    *,
    what: str,
    item_timeout_s: float,
    retries: int,
) -> int:
    """Upload ``items`` as ``mission_type``; returns the final MISSION_ACK result (0 = accepted).

    Raises :class:`LinkLost` when the heartbeat stops and :class:`CommandTimeout` when the vehicle
    stays silent through ``retries`` resends.
    """
    count = len(items)
    link.ensure_link(what)
    sub = link.subscribe(
        ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"],
        lambda m: (
            m.get_srcComponent() == link.target_component
            and (getattr(m, "mission_type", 0) or 0) == mission_type
        ),
    )

    def send_count() -> None:
        link.send(
            mavlink.MAVLink_mission_count_message(
                link.target_system, link.target_component, count, mission_type
            )
        )

    try:
        send_count()
        last_sent: int | None = None
        silent = 0
        last_resent = False  # the last item went out again: its ACK may have been lost before
        while True:
            msg = await _next(link, sub, item_timeout_s, what)
            if msg is None:
                silent += 1
                if last_resent and await _holds(link, items, mission_type, item_timeout_s, retries):
                    log.info("%s: final ACK lost, the vehicle holds the upload", what)
                    return mavlink.MAV_MISSION_ACCEPTED
                if silent > retries:
                    raise CommandTimeout(what, item_timeout_s * (retries + 1))
                if last_sent is None:
                    send_count()
                else:
                    link.send(items[last_sent].to_message(link, last_sent, mission_type))
                    last_resent = last_sent == count - 1
                continue
            silent = 0
            mtype = msg.get_type()
            if mtype in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
                seq = int(msg.seq)
                if 0 <= seq < count:
                    link.send(items[seq].to_message(link, seq, mission_type))
                    last_sent = seq
                else:
                    log.warning("%s: vehicle requested seq %d of %d", what, seq, count)
                continue
            # MISSION_ACK
            result = int(msg.type)
            if result == mavlink.MAV_MISSION_ACCEPTED:
                if count == 0 or last_sent is not None:
                    return result
                continue  # a stale ACK of an earlier transfer, before any request of ours
            if result == mavlink.MAV_MISSION_INVALID_SEQUENCE:
                log.info("%s: NACK (invalid sequence), upload continues", what)
                continue
            if last_resent and await _holds(link, items, mission_type, item_timeout_s, retries):
                log.info(
                    "%s: final ACK lost (%s to the re-sent item), the vehicle holds the upload", what, result
                )
                return mavlink.MAV_MISSION_ACCEPTED
            return result
    finally:
        link.unsubscribe(sub)


async def _holds(
    link: MavlinkLink, items: list[Item], mission_type: int, timeout_s: float, retries: int
) -> bool:
    """Whether the vehicle stores ``items``: its count and its last item are ours (a short download)."""
    count = len(items)
    if count == 0:
        return False
    want = items[-1].to_message(link, count - 1, mission_type)
    sub = link.subscribe(
        ["MISSION_COUNT", "MISSION_ITEM_INT"],
        lambda m: (
            m.get_srcComponent() == link.target_component
            and (getattr(m, "mission_type", 0) or 0) == mission_type
        ),
    )
    ask_count = mavlink.MAVLink_mission_request_list_message(
        link.target_system, link.target_component, mission_type
    )
    ask_item = mavlink.MAVLink_mission_request_int_message(
        link.target_system, link.target_component, count - 1, mission_type
    )
    try:
        got = await _exchange(link, sub, ask_count, "MISSION_COUNT", timeout_s, retries)
        if got is None or int(got.count) != count:
            return False
        item = await _exchange(link, sub, ask_item, "MISSION_ITEM_INT", timeout_s, retries)
        link.send(
            mavlink.MAVLink_mission_ack_message(
                link.target_system, link.target_component, mavlink.MAV_MISSION_ACCEPTED, mission_type
            )
        )
        return (
            item is not None
            and int(item.seq) == count - 1
            and (item.command, item.x, item.y) == (want.command, want.x, want.y)
            and math.isclose(item.z, want.z, abs_tol=0.01)
        )
    finally:
        link.unsubscribe(sub)


async def _exchange(
    link: MavlinkLink, sub: Subscription, ask: Any, answer: str, timeout_s: float, retries: int
) -> Any | None:
    """Send ``ask`` until a message of type ``answer`` comes (at most ``retries + 1`` sends)."""
    for _ in range(retries + 1):
        link.send(ask)
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            msg = await _next(link, sub, remaining, "mission check")
            if msg is not None and msg.get_type() == answer:
                return msg
    return None


async def _next(link: MavlinkLink, sub: Subscription, timeout_s: float, what: str) -> Any | None:
    """The next protocol message within ``timeout_s``, checking the heartbeat while waiting."""
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0:
        msg = await sub.get(min(remaining, 0.1))
        if msg is not None:
            return msg
        link.ensure_link(what)
    return None


def fence_items(fence: FenceSpec) -> list[Item]:
    """The fence's inclusion polygon and circle as MISSION_TYPE_FENCE items (ValueError: < 3 vertices)."""
    items: list[Item] = []
    if fence.polygon:
        if len(fence.polygon) < 3:
            raise ValueError("fence polygon needs at least 3 vertices")
        n = len(fence.polygon)
        for vlat, vlon in fence.polygon:
            items.append(
                Item(
                    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                    mavlink.MAV_FRAME_GLOBAL,
                    vlat,
                    vlon,
                    0.0,
                    param1=n,
                )
            )
    if fence.circle is not None:
        c = fence.circle
        items.append(
            Item(
                mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
                mavlink.MAV_FRAME_GLOBAL,
                c.lat,
                c.lon,
                0.0,
                param1=c.radius_m,
            )
        )
    return items


def mission_items(points: list[MissionPoint], home: Telemetry | None) -> list[Item]:
    """Waypoints above home; with ``home`` (ArduPilot: seq 0 is home, it overwrites it, but it must
    be there) a home item first."""
    items: list[Item] = []
    if home is not None:
        items.append(
            Item(
                mavlink.MAV_CMD_NAV_WAYPOINT,
                mavlink.MAV_FRAME_GLOBAL,
                home.home_lat or 0.0,
                home.home_lon or 0.0,
                home.home_alt_amsl or 0.0,
            )
        )
    for p in points:
        items.append(
            Item(
                mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, p.lat, p.lon, p.alt_rel_m
            )
        )
    return items
