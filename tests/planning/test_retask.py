"""Re-tasking a dropped drone's share (gcs.planning.retask) on real numpy/shapely data.

A 200 x 100 m field split into four 50 m wide columns, one lawnmower per drone (swath 10 m);
the tracks flown so far are rasterised with seen_grid, exactly as the daemon does
(tests/planning/retask_field.py).
"""

import pytest

from gcs.planning.retask import Candidate, gap_route, propose_retask, share_gap
from gcs.planning.seen import seen_grid
from tests.planning.retask_field import FIELD, SWATH, candidates, column, cut, situation, track


def test_dropped_at_40_percent_its_unseen_share_goes_to_the_others_and_closes_the_gap() -> None:
    grid, share = situation(0.4)
    assert 83.0 <= grid.covered_pct <= 88.0  # a quarter of the field, 60 % of it unseen
    proposal = propose_retask(grid, "drone-2", share, SWATH, candidates())
    assert proposal.verdict == "proposed", proposal.reason
    assert proposal.gap_m2 == pytest.approx(0.6 * 5000, rel=0.08)
    assert proposal.gap["coordinates"]
    assert {leg.ident for leg in proposal.legs} <= {"drone-1", "drone-3", "drone-4"}
    assert all(leg.energy_wh <= leg.margin_wh and leg.time_s > 0 for leg in proposal.legs)
    flown = sum(leg.survey_m for leg in proposal.legs)
    assert 0.55 * 540 <= flown <= 0.7 * 540  # ~60 % of its 540 m path (5 legs, 4 turns)
    # flying the proposal (at the planned height) closes the gap: the field is seen whole
    legs = [[(a, b, 20.0) for a, b in leg.points] for leg in proposal.legs]
    tracks = [track(column(k)) for k in (0, 2, 3)] + [track(cut(column(1), 0.4)), *legs]
    assert seen_grid(FIELD, tracks, SWATH, 20.0).covered_pct >= 99.5


def test_a_finished_share_needs_nothing_and_an_unflown_one_all_of_it() -> None:
    grid, share = situation(1.0)
    done = propose_retask(grid, "drone-2", share, SWATH, candidates())
    assert done.verdict == "nothing_to_do" and not done.legs
    grid0, _ = situation(0.0)
    _, gap = share_gap(grid0, share, SWATH)
    route = gap_route(grid0, share, gap, SWATH)
    assert route is not None and route.length == pytest.approx(540.0, abs=1.0)


def test_short_margins_split_by_margin_or_refuse_with_the_numbers() -> None:
    grid, share = situation(0.4)
    poor = propose_retask(grid, "drone-2", share, SWATH, candidates(margin_wh=1.0))
    assert poor.verdict == "not_feasible" and "Wh" in poor.reason and poor.gap_m2 > 2500
    assert not poor.legs and poor.gap["coordinates"]  # the gap is still named
    nobody = propose_retask(grid, "drone-2", share, SWATH, [])
    assert nobody.verdict == "not_feasible" and "no drone" in nobody.reason
    # one rich drone and two poor ones: the rich one takes (almost) everything
    mixed = [
        c if c.ident != "drone-1" else Candidate(c.ident, c.start, c.home, 100.0, 5.0, 300.0)
        for c in candidates(2.0)
    ]
    rich = propose_retask(grid, "drone-2", share, SWATH, mixed)
    assert rich.verdict == "proposed", rich.reason
    assert all(leg.energy_wh <= leg.margin_wh for leg in rich.legs)
    assert max(rich.legs, key=lambda g: g.survey_m).ident == "drone-1"
