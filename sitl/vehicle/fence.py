"""The geofence: FENCE_TYPE checks (altitude, home circle, uploaded zones) and FENCE_ACTION on a breach."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.mission import FenceZone
from sitl.vehicle.constants import (
    AUTO,
    BRAKE,
    LAND,
    RTL,
    SEV_NOTICE,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class Fence:
    """Owns the fence state (uploaded zones, breach bits and counters); checked every 0.1 s of sim time."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v
        self.zones: list[FenceZone] = []
        self.breaches = 0
        self.breach_count = 0
        self.breach_time_ms = 0
        self.breach_type = 0
        self.next_check = 0.0

    def enabled(self) -> bool:
        """FENCE_ENABLE is set."""
        v = self.v
        return v.params["FENCE_ENABLE"] != 0

    def breached_types(self) -> int:
        """Bitmask of breached fence types (1 max alt, 2 home circle, 4 uploaded polygons/circles)."""
        v = self.v
        ftype = int(v.params["FENCE_TYPE"])
        b = v.belief()
        hn, he, hd = v.home_ned
        out = 0
        if ftype & 1 and -(b[2] - hd) > v.params["FENCE_ALT_MAX"]:
            out |= 1
        if ftype & 2 and math.hypot(b[0] - hn, b[1] - he) > v.params["FENCE_RADIUS"]:
            out |= 2
        if ftype & 4 and self.zones:
            for z in self.zones:
                if z.contains(b[0], b[1]) != z.inclusion:
                    out |= 4
                    break
        return out

    def check(self) -> None:
        """New breaches count, say 'Fence Breached' and run FENCE_ACTION (RTL, LAND or BRAKE)."""
        v = self.v
        if not self.enabled() or v.landed:
            self.breaches = 0
            return
        if not v.armed:
            return
        now = self.breached_types()
        new = now & ~self.breaches
        self.breaches = now
        if not new:
            return
        self.breach_count += 1
        self.breach_time_ms = int(v.t * 1000)
        self.breach_type = mav.FENCE_BREACH_BOUNDARY if new & 6 else mav.FENCE_BREACH_MAXALT
        v.statustext(SEV_NOTICE, "Fence Breached")
        action = int(v.params["FENCE_ACTION"])
        if action == 0 or v.mode == LAND or (v.mode == AUTO and v.auto.landing):
            return
        if action in (1, 3, 5):
            if v.mode != RTL and not (v.gps_ok and v.set_mode(RTL)):
                v.set_mode(LAND)
        elif action == 2 or (action == 4 and not (v.gps_ok and v.set_mode(BRAKE))):
            v.set_mode(LAND)
