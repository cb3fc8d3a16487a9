"""Private: the MAVLink mission upload protocol (missions, fences, rally points).

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
  at most ``retries`` times in a row, then :class:`CommandTimeout`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

from agent.autopilot.base import CommandTimeout
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
        while True:
            msg = await _next(link, sub, item_timeout_s, what)
            if msg is None:
                silent += 1
                if silent > retries:
                    raise CommandTimeout(what, item_timeout_s * (retries + 1))
                if last_sent is None:
                    send_count()
                else:
                    link.send(items[last_sent].to_message(link, last_sent, mission_type))
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
            return result
    finally:
        link.unsubscribe(sub)


async def _next(link: MavlinkLink, sub: Subscription, timeout_s: float, what: str) -> Any | None:
    """The next protocol message within ``timeout_s``, checking the heartbeat while waiting."""
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0:
        msg = await sub.get(min(remaining, 0.1))
        if msg is not None:
            return msg
        link.ensure_link(what)
    return None
