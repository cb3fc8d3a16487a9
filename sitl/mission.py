"""Mission protocol (upload/download/clear) and stored missions/fences, as ArduPilot does it.

* Upload: MISSION_COUNT -> the vehicle requests every item (MISSION_REQUEST_INT, or the legacy
  MISSION_REQUEST when ``legacy_request`` is set) -> MISSION_ITEM_INT or MISSION_ITEM -> MISSION_ACK.
  An out-of-sequence item gets a NACK (MAV_MISSION_INVALID_SEQUENCE) but the upload goes on; requests
  are resent after ``RESEND_S`` of silence and the upload is cancelled after ``TIMEOUT_S``.
  The stored list is replaced atomically when the last item arrives.
* Download: MISSION_REQUEST_LIST -> MISSION_COUNT; each MISSION_REQUEST_INT / MISSION_REQUEST is answered
  with MISSION_ITEM_INT / MISSION_ITEM. Seq 0 of a MISSION download is the current home.
* Mission type MISSION keeps seq 0 as home (the uploaded seq 0 is ignored, like ArduPilot); FENCE items
  use MAV_CMD_NAV_FENCE_* commands (5001-5004, 5000 return point); RALLY items are stored only.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from sitl.dialect import mavlink as mav
from sitl.physics import latlon_to_local

RESEND_S = 1.0
TIMEOUT_S = 8.0
MAX_ITEMS = 700

MISSION = mav.MAV_MISSION_TYPE_MISSION
FENCE = mav.MAV_MISSION_TYPE_FENCE
RALLY = mav.MAV_MISSION_TYPE_RALLY

GLOBAL_FRAMES_AMSL = (mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_INT)
SUPPORTED_FRAMES = (
    mav.MAV_FRAME_GLOBAL,
    mav.MAV_FRAME_GLOBAL_INT,
    mav.MAV_FRAME_GLOBAL_RELATIVE_ALT,
    mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    mav.MAV_FRAME_GLOBAL_TERRAIN_ALT,
    mav.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    mav.MAV_FRAME_MISSION,
)


@dataclass(slots=True)
class MissionItem:
    """One stored item; ``x``/``y`` are lat/lon in degrees*1e7 whatever message carried them."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = MISSION

    @property
    def lat(self) -> float:
        """Latitude in degrees."""
        return self.x / 1e7

    @property
    def lon(self) -> float:
        """Longitude in degrees."""
        return self.y / 1e7


@dataclass(slots=True)
class FenceZone:
    """An inclusion/exclusion polygon (local NE vertices) or circle (local NE centre + radius)."""

    inclusion: bool
    polygon: list[tuple[float, float]] = field(default_factory=list)
    centre: tuple[float, float] | None = None
    radius: float = 0.0

    def contains(self, n: float, e: float) -> bool:
        """True if the local point lies inside the zone."""
        if self.centre is not None:
            return math.hypot(n - self.centre[0], e - self.centre[1]) <= self.radius
        inside = False
        pts = self.polygon
        k = len(pts)
        for i in range(k):
            y1, x1 = pts[i]
            y2, x2 = pts[(i + 1) % k]
            if (y1 > n) != (y2 > n):
                x_cross = x1 + (n - y1) * (x2 - x1) / (y2 - y1)
                if e < x_cross:
                    inside = not inside
        return inside


def build_fence(items: list[MissionItem], lat0: float, lon0: float) -> list[FenceZone]:
    """Group FENCE items into zones in the vehicle's local frame (consecutive polygon vertices)."""
    zones: list[FenceZone] = []
    i = 0
    while i < len(items):
        it = items[i]
        if it.command in (
            mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
        ):
            count = max(1, int(it.param1))
            verts = [latlon_to_local(lat0, lon0, v.lat, v.lon) for v in items[i : i + count]]
            if len(verts) >= 3:
                incl = it.command == mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
                zones.append(FenceZone(inclusion=incl, polygon=verts))
            i += count
            continue
        if it.command in (mav.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, mav.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION):
            zones.append(
                FenceZone(
                    inclusion=it.command == mav.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
                    centre=latlon_to_local(lat0, lon0, it.lat, it.lon),
                    radius=float(it.param1),
                )
            )
        i += 1
    return zones


def item_from_msg(msg: mav.MAVLink_message) -> MissionItem:
    """MISSION_ITEM_INT or legacy MISSION_ITEM (float degrees) to a stored item."""
    if msg.get_type() == "MISSION_ITEM":
        x, y = round(msg.x * 1e7), round(msg.y * 1e7)
    else:
        x, y = int(msg.x), int(msg.y)
    return MissionItem(
        seq=msg.seq,
        frame=msg.frame,
        command=msg.command,
        current=msg.current,
        autocontinue=msg.autocontinue,
        param1=msg.param1,
        param2=msg.param2,
        param3=msg.param3,
        param4=msg.param4,
        x=x,
        y=y,
        z=msg.z,
        mission_type=getattr(msg, "mission_type", MISSION),
    )


@dataclass(slots=True)
class _Upload:
    mission_type: int
    count: int
    items: list[MissionItem]
    next_seq: int
    last_rx: float
    last_req: float


class MissionProtocol:
    """Per-vehicle mission transfer state machine; sends through ``send`` and stores in ``stores``.

    ``home_item`` supplies seq 0 for MISSION downloads, ``can_clear`` vetoes MISSION_CLEAR_ALL (ArduPilot
    refuses it while the mission runs) and ``on_stored`` is told when a list was replaced.
    """

    def __init__(
        self,
        sysid: int,
        send: Callable[[mav.MAVLink_message], None],
        home_item: Callable[[], MissionItem],
        can_clear: Callable[[int], bool],
        on_stored: Callable[[int], None],
        legacy_request: bool = False,
    ) -> None:
        self.sysid = sysid
        self.send = send
        self.home_item = home_item
        self.can_clear = can_clear
        self.on_stored = on_stored
        self.legacy_request = legacy_request
        self.stores: dict[int, list[MissionItem]] = {MISSION: [], FENCE: [], RALLY: []}
        self.upload: _Upload | None = None
        self.gcs_sys = 255
        self.gcs_comp = 190

    # -- stored lists ------------------------------------------------------------------------------
    def mission_items(self) -> list[MissionItem]:
        """MISSION list including seq 0 (home placeholder; use :meth:`download_item` for the real home)."""
        return self.stores[MISSION]

    def count(self, mission_type: int) -> int:
        """Number of items a download of ``mission_type`` reports (MISSION includes home at seq 0)."""
        n = len(self.stores.get(mission_type, []))
        if mission_type == MISSION:
            return max(1, n)
        return n

    def download_item(self, mission_type: int, seq: int) -> MissionItem | None:
        """Item ``seq`` as a download returns it (seq 0 of MISSION is the live home)."""
        if mission_type == MISSION and seq == 0:
            return self.home_item()
        items = self.stores.get(mission_type, [])
        if 0 <= seq < len(items):
            return items[seq]
        return None

    # -- message handling --------------------------------------------------------------------------
    def _ack(self, result: int, mission_type: int) -> None:
        self.send(mav.MAVLink_mission_ack_message(self.gcs_sys, self.gcs_comp, result, mission_type))

    def _request(self, seq: int, mission_type: int) -> None:
        if self.legacy_request:
            self.send(mav.MAVLink_mission_request_message(self.gcs_sys, self.gcs_comp, seq, mission_type))
        else:
            self.send(mav.MAVLink_mission_request_int_message(self.gcs_sys, self.gcs_comp, seq, mission_type))

    def handle(self, msg: mav.MAVLink_message, now: float) -> bool:
        """Handle a mission-protocol message; returns False if ``msg`` is not one."""
        t = msg.get_type()
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        mtype = getattr(msg, "mission_type", MISSION)
        if t == "MISSION_COUNT":
            self.gcs_sys, self.gcs_comp = src_sys, src_comp
            if mtype not in self.stores:
                self._ack(mav.MAV_MISSION_UNSUPPORTED, mtype)
                return True
            if msg.count > MAX_ITEMS:
                self._ack(mav.MAV_MISSION_NO_SPACE, mtype)
                return True
            if msg.count == 0:
                self.upload = None
                self.stores[mtype] = []
                self.on_stored(mtype)
                self._ack(mav.MAV_MISSION_ACCEPTED, mtype)
                return True
            self.upload = _Upload(mtype, msg.count, [], 0, now, now)
            self._request(0, mtype)
            return True
        if t in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            up = self.upload
            if up is None or mtype != up.mission_type:
                self._ack(mav.MAV_MISSION_ERROR, mtype)
                return True
            if msg.seq != up.next_seq:
                # ArduPilot NACKs and keeps waiting for the item it asked for.
                if msg.seq < up.next_seq:
                    return True  # duplicate of an item we already have: ignore
                self._ack(mav.MAV_MISSION_INVALID_SEQUENCE, mtype)
                return True
            item = item_from_msg(msg)
            item.mission_type = mtype
            if item.frame not in SUPPORTED_FRAMES and item.frame != mav.MAV_FRAME_LOCAL_NED:
                self._ack(mav.MAV_MISSION_UNSUPPORTED_FRAME, mtype)
                return True
            up.items.append(item)
            up.next_seq += 1
            up.last_rx = up.last_req = now
            if up.next_seq >= up.count:
                self.stores[mtype] = up.items
                self.upload = None
                self.on_stored(mtype)
                self._ack(mav.MAV_MISSION_ACCEPTED, mtype)
            else:
                self._request(up.next_seq, mtype)
            return True
        if t == "MISSION_REQUEST_LIST":
            self.gcs_sys, self.gcs_comp = src_sys, src_comp
            if mtype not in self.stores:
                self._ack(mav.MAV_MISSION_UNSUPPORTED, mtype)
                return True
            self.send(mav.MAVLink_mission_count_message(src_sys, src_comp, self.count(mtype), mtype))
            return True
        if t in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            item_ = self.download_item(mtype, msg.seq)
            if item_ is None:
                self._ack(mav.MAV_MISSION_INVALID_SEQUENCE, mtype)
                return True
            head = (
                src_sys, src_comp, msg.seq, item_.frame, item_.command, item_.current, item_.autocontinue,
                item_.param1, item_.param2, item_.param3, item_.param4,
            )  # fmt: skip
            out: mav.MAVLink_message
            if t == "MISSION_REQUEST_INT":
                out = mav.MAVLink_mission_item_int_message(*head, item_.x, item_.y, item_.z, mtype)
            else:  # legacy MISSION_ITEM carries degrees as floats
                out = mav.MAVLink_mission_item_message(*head, item_.x / 1e7, item_.y / 1e7, item_.z, mtype)
            self.send(out)
            return True
        if t == "MISSION_CLEAR_ALL":
            if mtype not in self.stores:
                self._ack(mav.MAV_MISSION_UNSUPPORTED, mtype)
                return True
            if not self.can_clear(mtype):
                self._ack(mav.MAV_MISSION_ERROR, mtype)
                return True
            self.stores[mtype] = []
            self.on_stored(mtype)
            self._ack(mav.MAV_MISSION_ACCEPTED, mtype)
            return True
        # MISSION_ACK from the GCS at the end of a download needs nothing.
        return t == "MISSION_ACK"

    def tick(self, now: float) -> None:
        """Resend the outstanding request, or give the upload up, on wall-clock timeouts."""
        up = self.upload
        if up is None:
            return
        if now - up.last_rx > TIMEOUT_S:
            self.upload = None
            self._ack(mav.MAV_MISSION_OPERATION_CANCELLED, up.mission_type)
            return
        if now - up.last_req > RESEND_S:
            up.last_req = now
            self._request(up.next_seq, up.mission_type)
