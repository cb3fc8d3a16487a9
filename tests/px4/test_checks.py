"""The hold check itself, on made-up fixes (no PX4): it must pass a hovering drone whose EKF velocity
is noisy and fail one that flies on or creeps away."""

from __future__ import annotations

import math

from protocol.geo import offset_latlon
from tests.px4.checks import SPEED_WINDOW_S, STOPPED_MPS, ground_speeds, hold_verdict
from tests.px4.observer import Fix
from tests.px4.rig import HOME

RATE_HZ = 20.0


def track(seconds: float, north_mps: float, wobble_m: float = 0.0, ekf_mps: float = 0.0) -> list[Fix]:
    """Fixes of a drone moving north at ``north_mps``, wobbling ``wobble_m`` at 1.5 Hz, its reported
    velocity ``ekf_mps`` whatever it does (as SIH's hover noise reads)."""
    out = []
    for k in range(int(seconds * RATE_HZ)):
        t = k / RATE_HZ
        lat, lon = offset_latlon(HOME[0], HOME[1], north_mps * t + wobble_m * math.sin(9.4 * t), 0.0)
        out.append(Fix(100.0 + t, lat, lon, 10.0, ekf_mps or north_mps))
    return out


def test_a_hovering_drone_with_noisy_velocity_holds() -> None:
    fastest, drift = hold_verdict(track(10.0, 0.0, wobble_m=0.05, ekf_mps=0.7))
    assert fastest < STOPPED_MPS and drift < 0.2


def test_a_drone_that_flies_on_fails() -> None:
    fastest, drift = hold_verdict(track(10.0, 3.0))
    assert fastest > 2.9 and drift > 25.0


def test_a_slow_creep_fails_on_speed_or_drift() -> None:
    assert hold_verdict(track(10.0, 0.6))[0] > STOPPED_MPS
    assert hold_verdict(track(10.0, 0.4))[1] > 3.0


def test_speeds_span_the_window_of_vehicle_time() -> None:
    speeds = ground_speeds(track(3.0, 1.0))
    assert len(speeds) == int((3.0 - SPEED_WINDOW_S) * RATE_HZ)
    assert all(abs(s - 1.0) < 0.01 for s in speeds)


def test_a_fly_back_fails() -> None:
    """Stopped, then 1.5 m back at 0.55 m/s (what PX4 did after braking past its pause point)."""
    still = track(3.0, 0.0)
    back = [
        Fix(f.t + 3.0, *offset_latlon(HOME[0], HOME[1], -0.55 * (f.t - 100.0), 0.0), 10.0, 0.55)
        for f in track(2.7, 0.0)
    ]
    assert hold_verdict(still + back)[0] > STOPPED_MPS
