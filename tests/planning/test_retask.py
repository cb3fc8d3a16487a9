"""Re-tasking a dropped drone's share (gcs.planning.retask) on real numpy/shapely data.

A 200 x 100 m field split into four 50 m wide columns, one lawnmower per drone (swath 10 m);
the tracks flown so far are rasterised with seen_grid, exactly as the daemon does.
"""

import numpy as np
import pytest

from gcs.planning.geodesy import LocalFrame
from gcs.planning.retask import Candidate, gap_route, propose_retask, share_gap
from gcs.planning.seen import SeenGrid, seen_grid

FRAME = LocalFrame(47.0, 8.0)
SWATH = 10.0
FIELD = [(float(a), float(b)) for a, b in FRAME.points_to_geodetic([(0, 0), (200, 0), (200, 100), (0, 100)])]


def _ll(points_en: list[tuple[float, float]]) -> list[tuple[float, float]]:
    return [(float(a), float(b)) for a, b in FRAME.points_to_geodetic(points_en)]


def _column(k: int) -> list[tuple[float, float]]:
    """Drone k's share: north-south legs over x in [50k, 50k + 50], 5 m from each side."""
    pts: list[tuple[float, float]] = []
    for j, x in enumerate(np.arange(50 * k + SWATH / 2, 50 * (k + 1), SWATH)):
        ys = (0.0, 100.0) if j % 2 == 0 else (100.0, 0.0)
        pts += [(float(x), ys[0]), (float(x), ys[1])]
    return pts


def _cut(points: list[tuple[float, float]], fraction: float) -> list[tuple[float, float]]:
    """The first ``fraction`` of a polyline by length (what a drone flew before it dropped)."""
    from shapely.geometry import LineString
    from shapely.ops import substring

    line = LineString(points)
    return [(float(x), float(y)) for x, y in substring(line, 0, fraction * line.length).coords]


def _track(points_en: list[tuple[float, float]]) -> list[tuple[float, float, float]]:
    return [(a, b, 20.0) for a, b in _ll(points_en)]


def _candidates(margin_wh: float = 50.0) -> list[Candidate]:
    home = _ll([(100.0, -20.0)])[0]
    return [
        Candidate(f"drone-{k + 1}", _ll([_column(k)[-1]])[0], home, margin_wh, 5.0, 300.0) for k in (0, 2, 3)
    ]


def _situation(fraction: float) -> tuple[SeenGrid, list[tuple[float, float]]]:
    tracks = [_track(_column(k)) for k in (0, 2, 3)] + [_track(_cut(_column(1), fraction))]
    return seen_grid(FIELD, tracks, SWATH, 20.0), _ll(_column(1))


def test_dropped_at_40_percent_its_unseen_share_goes_to_the_others_and_closes_the_gap() -> None:
    grid, share = _situation(0.4)
    assert 83.0 <= grid.covered_pct <= 88.0  # a quarter of the field, 60 % of it unseen
    proposal = propose_retask(grid, "drone-2", share, SWATH, _candidates())
    assert proposal.verdict == "proposed", proposal.reason
    assert proposal.gap_m2 == pytest.approx(0.6 * 5000, rel=0.08)
    assert proposal.gap["coordinates"]
    assert {leg.ident for leg in proposal.legs} <= {"drone-1", "drone-3", "drone-4"}
    assert all(leg.energy_wh <= leg.margin_wh and leg.time_s > 0 for leg in proposal.legs)
    flown = sum(leg.survey_m for leg in proposal.legs)
    assert 0.55 * 540 <= flown <= 0.7 * 540  # ~60 % of its 540 m path (5 legs, 4 turns)
    # flying the proposal (at the planned height) closes the gap: the field is seen whole
    legs = [[(a, b, 20.0) for a, b in leg.points] for leg in proposal.legs]
    tracks = [_track(_column(k)) for k in (0, 2, 3)] + [_track(_cut(_column(1), 0.4)), *legs]
    assert seen_grid(FIELD, tracks, SWATH, 20.0).covered_pct >= 99.5


def test_a_finished_share_needs_nothing_and_an_unflown_one_all_of_it() -> None:
    grid, share = _situation(1.0)
    done = propose_retask(grid, "drone-2", share, SWATH, _candidates())
    assert done.verdict == "nothing_to_do" and not done.legs
    grid0, _ = _situation(0.0)
    _, gap = share_gap(grid0, share, SWATH)
    route = gap_route(grid0, share, gap, SWATH)
    assert route is not None and route.length == pytest.approx(540.0, abs=1.0)


def test_short_margins_split_by_margin_or_refuse_with_the_numbers() -> None:
    grid, share = _situation(0.4)
    poor = propose_retask(grid, "drone-2", share, SWATH, _candidates(margin_wh=1.0))
    assert poor.verdict == "not_feasible" and "Wh" in poor.reason and poor.gap_m2 > 2500
    assert not poor.legs and poor.gap["coordinates"]  # the gap is still named
    nobody = propose_retask(grid, "drone-2", share, SWATH, [])
    assert nobody.verdict == "not_feasible" and "no drone" in nobody.reason
    # one rich drone and two poor ones: the rich one takes (almost) everything
    mixed = [
        c if c.ident != "drone-1" else Candidate(c.ident, c.start, c.home, 100.0, 5.0, 300.0)
        for c in _candidates(2.0)
    ]
    rich = propose_retask(grid, "drone-2", share, SWATH, mixed)
    assert rich.verdict == "proposed", rich.reason
    assert all(leg.energy_wh <= leg.margin_wh for leg in rich.legs)
    assert max(rich.legs, key=lambda g: g.survey_m).ident == "drone-1"
