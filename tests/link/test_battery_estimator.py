"""The emergency monitor's battery estimator keeps running sums in a fixed ring: it must give what a
least-squares fit and a track sum over the samples in its window give (the old per-report work)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.cooperation.emergency import BatteryEstimator
from protocol.geo import distance_m, offset_latlon
from protocol.packets import Battery, Position, StatusReport

WINDOW = 20.0


def _status(t: float, pct: float, north: float, east: float) -> StatusReport:
    lat, lon = offset_latlon(47.39, 8.54, north, east)
    return StatusReport(
        time=1.7e9 + t,
        position=Position(lat=lat, lon=lon, alt_rel=10.0, alt_amsl=500.0),
        battery=Battery(pct=pct),
        armed=True,
        landed=False,
    )


@settings(max_examples=200, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.floats(WINDOW / BatteryEstimator.RESOLUTION + 0.01, 2.0),  # dt: every sample is kept
            st.floats(-0.5, 0.2),  # change of %
            st.floats(-20.0, 20.0),  # metres north
            st.floats(-20.0, 20.0),  # metres east
        ),
        min_size=2,
        max_size=400,
    )
)
def test_running_sums_match_a_fit_over_the_window(steps: list[tuple[float, float, float, float]]) -> None:
    estimator = BatteryEstimator(WINDOW)
    t, pct, north, east = 0.0, 90.0, 0.0, 0.0
    samples: list[StatusReport] = []
    for dt, dp, dn, de in steps:
        t, pct, north, east = t + dt, min(100.0, max(0.0, pct + dp)), north + dn, east + de
        report = _status(t, pct, north, east)
        estimator.add(report)
        samples.append(report)
    newest = samples[-1].time
    window = [s for s in samples if newest - s.time <= WINDOW]
    times = np.array([s.time - window[0].time for s in window])
    span = times[-1] - times[0]
    rate = estimator.drop_rate()
    if len(window) < 3 or span < WINDOW / 2:
        assert rate is None
    else:
        slope = float(np.polyfit(times, [s.battery.pct for s in window], 1)[0])
        assert rate == pytest.approx(max(-slope, 0.0), abs=1e-6)
    track = sum(
        distance_m(a.position.lat, a.position.lon, b.position.lat, b.position.lon)  # type: ignore[union-attr]
        for a, b in itertools.pairwise(window)
    )
    speed = estimator.ground_speed()
    if len(window) >= 2 and span > 0:
        expected = max(track / span, estimator.max_speed * 0.8)
        assert speed == (pytest.approx(expected, rel=1e-6) if expected > 0.05 else None)


def test_reports_closer_than_the_resolution_share_one_sample_and_memory_stays_fixed() -> None:
    estimator = BatteryEstimator(30.0)
    for k in range(3000):  # 5 minutes at 10 Hz, draining 0.1 %/s
        estimator.add(_status(k * 0.1, 95.0 - 0.01 * k, 0.5 * k, 0.0))
    assert estimator.drop_rate() == pytest.approx(0.1, rel=1e-3)
    assert estimator.ground_speed() == pytest.approx(5.0, rel=1e-3)
    assert estimator._count <= BatteryEstimator.RESOLUTION + 1
