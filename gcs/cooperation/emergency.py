"""Daemon-side emergency checks that duplicate the agent's (defence in depth).

The agent's exception monitor acts on its own; these checks run on the daemon from status
reports, so a broken companion computer, a fence the agent did not install, or an agent whose
battery thresholds are too optimistic is still caught. Each check is pure: it gets the latest
report (and a little history) and says whether the condition holds and why.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gcs.planning.geodesy import FloatArray, distance_m_array
from protocol.geo import distance_m
from protocol.packets import Geofence, StatusReport

IntArray = NDArray[np.intp]
NO_RETURN_MODES = ("RTL", "LAND")  # the return-home check does not apply: the drone returns or lands


def fence_violation(status: StatusReport, fence: Geofence | None) -> str | None:
    """Why the drone is outside ``fence`` (the one the daemon sent), or None."""
    p = status.position
    if fence is None or p is None or status.gps.fix < 3 or status.landed:
        return None
    return fence.violation(p.lat, p.lon, p.alt_rel)


class BatteryColumns:
    """Battery estimators of many drones as arrays, one row per slot, fed a whole status tick at once.

    Per row: the battery % drop rate and the ground speed from recent reports, both per *wall*
    second. Using the same clock for both makes the estimate independent of a simulator's
    speed-up, and of whether the autopilot reports current at all (only the percentage is used).

    Why arrays: at thousands of drones a Python object per drone fed per report cost the event
    loop microseconds a report; :meth:`add` takes one row per drone of a tick in one vectorised
    pass. O(1) per report and a fixed footprint: samples at least ``window_s / RESOLUTION``
    apart go into a preallocated ring (time, %, distance from the sample before), and the
    least-squares sums and the track length are kept as running sums. Each row follows exactly
    the arithmetic of one scalar estimator (:class:`BatteryEstimator` is a one-row view).
    """

    RESOLUTION = 50  # samples per window at most

    def __init__(self, window_s: float, capacity: int = 1) -> None:
        self.window_s = window_s
        self.size = self.RESOLUTION + 2
        n = max(1, capacity)
        self.ring = np.zeros((n, self.size, 3))  # t (from base), pct, segment length
        self.head = np.zeros(n, dtype=np.intp)  # index of the oldest sample
        self.count = np.zeros(n, dtype=np.intp)
        self.base = np.zeros(n)
        self.sums = np.zeros((n, 4))  # sum t, sum pct, sum t*t, sum t*pct
        self.track = np.zeros(n)  # sum of the segments of every sample but the oldest
        self.last = np.full((n, 3), np.nan)  # t, lat, lon of the last report taken (NaN t: none)
        self.point = np.zeros((n, 2))  # lat, lon of the newest sample in the ring
        self.max_speed = np.zeros(n)
        self.rate = np.full(n, np.nan)  # drop_rate() as of the last change of the row's history
        self.speed = np.full(n, np.nan)  # ground_speed() likewise

    @property
    def capacity(self) -> int:
        return len(self.head)

    def grow(self, capacity: int) -> None:
        """Room for ``capacity`` rows (new rows empty)."""
        extra = capacity - self.capacity
        if extra <= 0:
            return
        fresh = BatteryColumns(self.window_s, extra)
        for name in ("ring", "head", "count", "base", "sums", "track", "last", "point", "max_speed"):
            setattr(self, name, np.concatenate([getattr(self, name), getattr(fresh, name)]))
        for name in ("rate", "speed"):
            setattr(self, name, np.concatenate([getattr(self, name), getattr(fresh, name)]))

    def reset(self, slots: IntArray) -> None:
        """Forget the history of ``slots`` (a new drone in the slot, or its clock went back)."""
        self.ring[slots] = 0.0
        self.head[slots] = 0
        self.count[slots] = 0
        self.base[slots] = 0.0
        self.sums[slots] = 0.0
        self.track[slots] = 0.0
        self.last[slots] = np.nan
        self.point[slots] = 0.0
        self.max_speed[slots] = 0.0
        self.rate[slots] = np.nan
        self.speed[slots] = np.nan

    def add(self, slots: IntArray, t: FloatArray, pct: FloatArray, lat: FloatArray, lon: FloatArray) -> None:
        """One report per row of ``slots`` (distinct; armed, flying, positioned, with a battery %)."""
        if len(slots) == 0:
            return
        if len(np.unique(slots)) != len(slots):  # one drone twice: in order, one at a time
            for k in range(len(slots)):
                self.add(slots[k : k + 1], t[k : k + 1], pct[k : k + 1], lat[k : k + 1], lon[k : k + 1])
            return
        last = self.last[slots]
        dt = t - last[:, 0]  # NaN for a row without a report yet: neither back nor forward
        back = dt < 0
        went_back = bool(back.any())
        if went_back:  # the clock went back: start over
            self.reset(slots[back])
        # The fastest leg between reports; a drone that did not move cannot raise it (distance 0).
        moving = (dt > 0) & ((lat != last[:, 1]) | (lon != last[:, 2]))
        faster = slots[:0]
        if moving.any():
            m = slots[moving]
            speed = distance_m_array(last[moving, 1], last[moving, 2], lat[moving], lon[moving]) / dt[moving]
            up = speed > self.max_speed[m]
            faster = m[up]
            self.max_speed[faster] = speed[up]
        self.last[slots] = np.stack((t, lat, lon), axis=1)
        sampled = self._sample(slots, t, pct, lat, lon)
        if went_back or len(faster):  # every row whose history changed
            sampled = np.concatenate([faster, slots[back], sampled])
        self._estimate(sampled)

    def _estimate(self, slots: IntArray) -> None:
        """Refresh the cached :attr:`rate` and :attr:`speed` of ``slots``."""
        if len(slots):
            self.rate[slots] = self.drop_rate(slots)
            self.speed[slots] = self.ground_speed(slots)

    def _sample(
        self, slots: IntArray, t: FloatArray, pct: FloatArray, lat: FloatArray, lon: FloatArray
    ) -> IntArray:
        """Put each report into its ring unless it is closer than the resolution to the one before;
        the slots that took a sample."""
        count, head, size = self.count[slots], self.head[slots], self.size
        newest = (head + count - 1) % size
        newest_t = self.ring[slots, newest, 0] + self.base[slots]
        with np.errstate(invalid="ignore"):
            close = (count > 0) & (t - newest_t < self.window_s / self.RESOLUTION)
        take = ~close  # closer to the sample before than the ring's resolution: not a sample
        if not take.any():
            return slots[:0]
        s, t, pct, lat, lon, count = slots[take], t[take], pct[take], lat[take], lon[take], count[take]
        sampled = s
        first = count == 0
        segment = np.zeros(len(s))
        if not first.all():
            later = ~first
            point = self.point[s[later]]
            segment[later] = distance_m_array(point[:, 0], point[:, 1], lat[later], lon[later])
        self.base[s[first]] = t[first]
        self.point[s, 0], self.point[s, 1] = lat, lon
        full = count == size
        if full.any():
            self._expire(s[full])
        head, count = self.head[s], self.count[s]
        slot = (head + count) % size
        rel = t - self.base[s]
        self.ring[s, slot, 0], self.ring[s, slot, 1], self.ring[s, slot, 2] = rel, pct, segment
        count = count + 1
        self.count[s] = count
        sums = self.sums[s]
        sums[:, 0] += rel
        sums[:, 1] += pct
        sums[:, 2] += rel * rel
        sums[:, 3] += rel * pct
        self.sums[s] = sums
        grown = count > 1
        self.track[s[grown]] += segment[grown]
        for _ in range(size):  # bounded: each pass drops one sample of the rows still too long
            old = (self.count[s] > 1) & (rel - self.ring[s, self.head[s], 0] > self.window_s)
            if not old.any():
                break
            self._expire(s[old])
            s, rel = s[old], rel[old]
        return sampled

    def _expire(self, slots: IntArray) -> None:
        """Drop the oldest sample of each of ``slots`` from the ring and the sums."""
        head = self.head[slots]
        rel, pct = self.ring[slots, head, 0], self.ring[slots, head, 1]
        sums = self.sums[slots]
        sums[:, 0] -= rel
        sums[:, 1] -= pct
        sums[:, 2] -= rel * rel
        sums[:, 3] -= rel * pct
        self.sums[slots] = sums
        head = (head + 1) % self.size
        count = self.count[slots] - 1
        self.head[slots], self.count[slots] = head, count
        self.track[slots] = np.where(count > 0, self.track[slots] - self.ring[slots, head, 2], 0.0)

    def _span(self, slots: IntArray) -> FloatArray:
        head, count = self.head[slots], self.count[slots]
        newest = (head + count - 1) % self.size
        span: FloatArray = self.ring[slots, newest, 0] - self.ring[slots, head, 0]
        return span

    def drop_rate(self, slots: IntArray) -> FloatArray:
        """Least-squares % per wall second over the window (NaN until it spans half the window)."""
        n = self.count[slots]
        st, sp, stt, stp = self.sums[slots].T
        with np.errstate(invalid="ignore", divide="ignore"):
            denominator = n * stt - st * st
            ok = (n >= 3) & (self._span(slots) >= self.window_s / 2) & (denominator > 0)
            slope = (n * stp - st * sp) / np.where(ok, denominator, 1.0)
        return np.where(ok, np.maximum(-slope, 0.0), np.nan)

    def ground_speed(self, slots: IntArray) -> FloatArray:
        """Average speed over the window, or the fastest seen when hovering (return trips are flown
        fast); NaN with less than two samples or no movement."""
        dt = self._span(slots)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(dt > 0, self.track[slots] / np.where(dt > 0, dt, 1.0), 0.0)
        best = np.maximum(mean, self.max_speed[slots] * 0.8)
        return np.where((self.count[slots] >= 2) & (best > 0.05), best, np.nan)

    def view(self, slot: int) -> BatteryView:
        return BatteryView(self, slot)


class BatteryView:
    """One row of :class:`BatteryColumns` as the scalar estimator the return check reads."""

    __slots__ = ("_columns", "_slots")

    def __init__(self, columns: BatteryColumns, slot: int) -> None:
        self._columns = columns
        self._slots = np.array([slot], dtype=np.intp)

    def drop_rate(self) -> float | None:
        rate = float(self._columns.rate[self._slots[0]])
        return None if math.isnan(rate) else rate

    def ground_speed(self) -> float | None:
        speed = float(self._columns.speed[self._slots[0]])
        return None if math.isnan(speed) else speed

    @property
    def max_speed(self) -> float:
        return float(self._columns.max_speed[self._slots[0]])

    @property
    def _count(self) -> int:
        return int(self._columns.count[self._slots[0]])


class BatteryEstimator(BatteryView):
    """One drone's estimator fed one report at a time (a one-row :class:`BatteryColumns`)."""

    RESOLUTION = BatteryColumns.RESOLUTION
    __slots__ = ("window_s",)

    def __init__(self, window_s: float) -> None:
        super().__init__(BatteryColumns(window_s, 1), 0)
        self.window_s = window_s

    def add(self, status: StatusReport) -> None:
        p = status.position
        pct = status.battery.pct
        if pct is None or p is None or status.landed or not status.armed:
            return
        one = np.array
        self._columns.add(self._slots, one([status.time]), one([pct]), one([p.lat]), one([p.lon]))


def return_home_shortfall(
    status: StatusReport,
    home: tuple[float, float],
    estimator: BatteryView,
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
