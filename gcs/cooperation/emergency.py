"""Daemon-side emergency checks that duplicate the agent's (defence in depth).

The agent's exception monitor acts on its own; these checks run on the daemon from status
reports, so a broken companion computer, a fence the agent did not install, or an agent whose
battery thresholds are too optimistic is still caught. Each check is pure: it gets the latest
report (and a little history) and says whether the condition holds and why.
"""

from __future__ import annotations

import math
from array import array

from protocol.geo import distance_m
from protocol.packets import Geofence, StatusReport


def fence_violation(status: StatusReport, fence: Geofence | None) -> str | None:
    """Why the drone is outside ``fence`` (the one the daemon sent), or None."""
    p = status.position
    if fence is None or p is None or status.gps.fix < 3 or status.landed:
        return None
    return fence.violation(p.lat, p.lon, p.alt_rel)


class BatteryEstimator:
    """Battery % drop rate and ground speed from recent reports, both per *wall* second.

    Using the same clock for both makes the estimate independent of a simulator's speed-up,
    and of whether the autopilot reports current at all (only the percentage is used).

    O(1) per report and a fixed footprint (one per tracked drone, thousands at once): samples at
    least ``window_s / RESOLUTION`` apart go into a preallocated ring (time, %, distance from the
    sample before), and the least-squares sums and the track length are kept as running sums.
    """

    RESOLUTION = 50  # samples per window at most
    __slots__ = (
        "_base",
        "_count",
        "_head",
        "_last",
        "_point",
        "_ring",
        "_sums",
        "_track",
        "max_speed",
        "window_s",
    )

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self.max_speed = 0.0
        size = self.RESOLUTION + 2
        self._ring = array("d", bytes(8 * 3 * size))  # t (from _base), pct, segment length
        self._head = 0  # index of the oldest sample
        self._count = 0
        self._base = 0.0
        self._sums = [0.0, 0.0, 0.0, 0.0]  # sum t, sum pct, sum t*t, sum t*pct
        self._track = 0.0  # sum of the segments of every sample but the oldest
        self._last: tuple[float, float, float] | None = None  # t, lat, lon of the last report taken
        self._point = (0.0, 0.0)  # lat, lon of the newest sample in the ring

    def add(self, status: StatusReport) -> None:
        p = status.position
        pct = status.battery.pct
        if pct is None or p is None or status.landed or not status.armed:
            return
        t = status.time
        last = self._last
        if last is not None:
            dt = t - last[0]
            if dt < 0:  # the clock went back: start over
                self.__init__(self.window_s)  # type: ignore[misc]
                last = None
            elif dt > 0:
                self.max_speed = max(self.max_speed, distance_m(last[1], last[2], p.lat, p.lon) / dt)
        self._last = (t, p.lat, p.lon)
        ring, size = self._ring, len(self._ring) // 3
        if self._count:
            newest = (self._head + self._count - 1) % size
            if t - (ring[3 * newest] + self._base) < self.window_s / self.RESOLUTION:
                return  # closer to the sample before than the ring's resolution
            segment = distance_m(self._point[0], self._point[1], p.lat, p.lon)
        else:
            self._base = t
            segment = 0.0
        self._point = (p.lat, p.lon)
        if self._count == size:
            self._expire()
        slot = (self._head + self._count) % size
        rel = t - self._base
        ring[3 * slot], ring[3 * slot + 1], ring[3 * slot + 2] = rel, pct, segment
        self._count += 1
        sums = self._sums
        sums[0] += rel
        sums[1] += pct
        sums[2] += rel * rel
        sums[3] += rel * pct
        if self._count > 1:
            self._track += segment
        while self._count > 1 and rel - ring[3 * self._head] > self.window_s:
            self._expire()

    def _expire(self) -> None:
        """Drop the oldest sample from the ring and the sums."""
        ring, size = self._ring, len(self._ring) // 3
        i = 3 * self._head
        rel, pct = ring[i], ring[i + 1]
        sums = self._sums
        sums[0] -= rel
        sums[1] -= pct
        sums[2] -= rel * rel
        sums[3] -= rel * pct
        self._head = (self._head + 1) % size
        self._count -= 1
        if self._count:
            self._track -= ring[3 * self._head + 2]  # the new oldest's segment leaves the track
        else:
            self._track = 0.0

    def _span(self) -> float:
        size = len(self._ring) // 3
        newest = (self._head + self._count - 1) % size
        return self._ring[3 * newest] - self._ring[3 * self._head]

    def drop_rate(self) -> float | None:
        """Least-squares % per wall second over the window (None until it spans half the window)."""
        n = self._count
        if n < 3 or self._span() < self.window_s / 2:
            return None
        st, sp, stt, stp = self._sums
        denominator = n * stt - st * st
        if denominator <= 0:
            return None
        slope = (n * stp - st * sp) / denominator
        return max(-slope, 0.0)

    def ground_speed(self) -> float | None:
        """Average speed over the window, or the fastest seen when hovering (return trips are flown fast)."""
        if self._count < 2:
            return None
        dt = self._span()
        mean = self._track / dt if dt > 0 else 0.0
        best = max(mean, self.max_speed * 0.8)
        return best if best > 0.05 else None


def return_home_shortfall(
    status: StatusReport,
    home: tuple[float, float],
    estimator: BatteryEstimator,
    descent_mps: float,
    vehicle_time_scale: float,
    reserve_pct: float,
    safety: float,
) -> tuple[bool, str] | None:
    """(cannot make it home, explanation) or None while there is not enough history."""
    pct = status.battery.pct
    rate = estimator.drop_rate()
    speed = estimator.ground_speed()
    p = status.position
    if pct is None or p is None or rate is None or speed is None or rate <= 0:
        return None
    dist = distance_m(p.lat, p.lon, home[0], home[1])
    descent_wall_s = max(p.alt_rel, 0.0) / (descent_mps * vehicle_time_scale)
    time_home = dist / speed + descent_wall_s
    needed = rate * time_home * safety + reserve_pct
    text = (
        f"battery {pct:.0f}%, needs {needed:.0f}% to get home: {dist:.0f} m at the observed "
        f"{rate * 60:.2f} %/min and {speed:.1f} m/s, reserve {reserve_pct:.0f}%"
    )
    return pct < needed, text


def gps_lost(status: StatusReport) -> bool:
    return status.armed and not status.landed and status.gps.fix < 3


def finite(value: float) -> bool:
    return math.isfinite(value)
