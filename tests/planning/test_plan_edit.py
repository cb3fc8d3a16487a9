"""A re-tasked member's plan (gcs.missions.plan_edit): legs after its survey, before its return."""

from gcs.missions.plan_edit import extend_plan, ready_step, survey_alt, survey_points
from gcs.planning.mission import mission_from_paths
from protocol.actions import Goto, Land, ReturnToLaunch, Takeoff, Waypoints

PATH = [(47.0, 8.0), (47.001, 8.0), (47.001, 8.001)]
LEGS = [(47.002, 8.0), (47.002, 8.001), (47.003, 8.001)]


def test_legs_go_after_the_survey_barrier_and_before_the_return_with_steps_that_only_grow() -> None:
    plan = list(mission_from_paths([PATH], alt=20.0).plans[0].actions)
    assert ready_step(plan) == 2 and survey_points(plan) == PATH and survey_alt(plan, 5.0) == 20.0
    new, send, ready = extend_plan(plan, LEGS, 20.0, 4.0)
    assert ready == 2
    assert new[: len(plan) - 1] == plan[:-1]  # takeoff, goto, the survey (its barrier kept)
    assert [type(a) for a in send] == [Takeoff, Goto, Waypoints, ReturnToLaunch]
    assert new[len(plan) - 1 :] == send
    steps = [a.step for a in new]
    assert steps == sorted(steps) and send[0].step > max(a.step for a in plan)
    rtl, old = send[-1], plan[-1]
    assert isinstance(rtl, ReturnToLaunch) and isinstance(old, ReturnToLaunch)
    assert rtl.alt == old.alt  # the layered return altitude travels with it
    assert survey_points(send) == LEGS and not any(a.sync for a in send)


def test_a_land_home_return_stays_last_and_a_second_edit_goes_after_the_first() -> None:
    plan = list(
        mission_from_paths([PATH], alt=20.0, return_mode="land_home", homes_latlon=[(46.999, 8.0)])
        .plans[0]
        .actions
    )
    first, _, _ = extend_plan(plan, LEGS, 20.0, None)
    second, send, ready = extend_plan(first, LEGS[::-1], 20.0, None)
    assert isinstance(second[-1], Land) and isinstance(second[-2], Goto)
    assert ready == max(a.step for a in first if isinstance(a, Waypoints))  # after the first legs
    assert survey_points(second) == PATH + LEGS + LEGS[::-1]
    assert [a.step for a in second] == sorted(a.step for a in second)
    assert survey_points(send) == LEGS[::-1]
