"""Daemon-side emergency checks that duplicate the agent's (defence in depth).

The agent's exception monitor acts on its own; these checks run on the daemon from status
reports, so a broken companion computer, a fence the agent did not install, or an agent whose
battery thresholds are too optimistic is still caught. Each check is pure: it gets the latest
report (and a little history) and says whether the condition holds and why.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from protocol.geo import distance_m
from protocol.packets import Geofence, StatusReport


def fence_violation(status: StatusReport, fence: Geofence | None) -> str | None:
    """Why the drone is outside ``fence`` (the one the daemon sent), or None."""
    p = status.position
    if fence is None or p is None or status.gps.fix < 3 or status.landed:
        return None
    return fence.violation(p.lat, p.lon, p.alt_rel)


@dataclass
class BatteryEstimator:
    """Battery % drop rate and ground speed from recent reports, both per *wall* second.

    Using the same clock for both makes the estimate independent of a simulator's speed-up,
    and of whether the autopilot reports current at all (only the percentage is used).
    """

    window_s: float
    samples: deque[tuple[float, float, float, float, float]] = field(
        default_factory=deque
    )  # t, pct, lat, lon, alt
    max_speed: float = 0.0

    def add(self, status: StatusReport) -> None:
        p = status.position
        if status.battery.pct is None or p is None or status.landed or not status.armed:
            return
        if self.samples:
            t0, _, lat0, lon0, _ = self.samples[-1]
            dt = status.time - t0
            if dt > 0:
                self.max_speed = max(self.max_speed, distance_m(lat0, lon0, p.lat, p.lon) / dt)
        self.samples.append((status.time, status.battery.pct, p.lat, p.lon, p.alt_rel))
        while self.samples and status.time - self.samples[0][0] > self.window_s:
            self.samples.popleft()

    def drop_rate(self) -> float | None:
        """Least-squares % per wall second over the window (None until it spans half the window)."""
        if len(self.samples) < 3 or self.samples[-1][0] - self.samples[0][0] < self.window_s / 2:
            return None
        t = np.array([s[0] for s in self.samples])
        pct = np.array([s[1] for s in self.samples])
        slope = float(np.polyfit(t - t[0], pct, 1)[0])
        return max(-slope, 0.0)

    def ground_speed(self) -> float | None:
        """Average speed over the window, or the fastest seen when hovering (return trips are flown fast)."""
        if len(self.samples) < 2:
            return None
        first, last = self.samples[0], self.samples[-1]
        dt = last[0] - first[0]
        track = sum(
            distance_m(a[2], a[3], b[2], b[3])
            for a, b in zip(self.samples, list(self.samples)[1:], strict=False)
        )
        mean = track / dt if dt > 0 else 0.0
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
