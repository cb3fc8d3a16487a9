"""Task files: the fleetgcs format, CoUAS import, and the validation that prevents barrier deadlocks."""

from __future__ import annotations

import json

import pytest

from protocol.actions import GoBy, Goto, Land, Takeoff
from protocol.gcj02 import gcj02_to_wgs84, wgs84_to_gcj02
from protocol.geo import distance_m
from protocol.taskfile import TaskFile, TaskFileError, load_task_text, task_warnings


def couas_row(action_type: int, cid: int, step: int, sync: int, **fields: float) -> dict[str, float | int]:
    return {"Action_type": action_type, "CID": cid, "Step": step, "Sync": sync, **fields}


COUAS = [
    couas_row(0, 1, 0, 1, Alt=10),
    couas_row(0, 2, 0, 1, Alt=12),
    couas_row(1, 1, 1, 1, Lat=47.3978, Lon=8.5456, Alt=10),
    couas_row(2, 2, 1, 1, N=10, E=-5, Alt=12),
    couas_row(3, 1, 2, 0, Lat=0, Lon=0),
    couas_row(3, 2, 2, 0, Lat=47.3977, Lon=8.5457, Time=3.5),
]


def test_couas_file_converts_per_cid_in_file_order() -> None:
    task = load_task_text(json.dumps(COUAS))
    assert [p.cid for p in task.plans] == [1, 2]
    one, two = task.plans
    assert [type(a) for a in one.actions] == [Takeoff, Goto, Land]
    assert [type(a) for a in two.actions] == [Takeoff, GoBy, Land]
    assert one.actions[2] == Land(step=2)  # 0,0 means "land here"
    assert two.actions[2] == Land(step=2, lat=47.3977, lon=8.5457)
    # go-by Alt is the altitude to fly at: 12 m after a 12 m takeoff is no climb.
    assert two.actions[1] == GoBy(step=1, sync=True, north=10, east=-5, up=0)
    assert one.sync_steps() == two.sync_steps() == [0, 1]


def _altitudes(actions: list[object]) -> list[float]:
    """The altitude each action leaves the drone at, starting on the ground."""
    alt, out = 0.0, []
    for action in actions:
        if isinstance(action, Takeoff | Goto):
            alt = action.alt
        elif isinstance(action, GoBy):
            alt += action.up
        elif isinstance(action, Land):
            alt = 0.0
        out.append(alt)
    return out


def psa_shaped_file(alt: float = 10.0) -> list[dict[str, float | int]]:
    """Two drones, 15 rows each, go-by at the takeoff altitude, syncs at steps 0 and 9,
    rows of the two drones interleaved (the shape of the CoUAS two-drone example)."""
    rows: list[dict[str, float | int]] = []
    for step in range(15):
        for cid in (1, 2):
            if step == 0:
                rows.append(couas_row(0, cid, 0, 1, Alt=alt))
            elif step == 14:
                rows.append(couas_row(3, cid, 14, 0, Lat=0, Lon=0))
            else:
                rows.append(couas_row(2, cid, step, int(step == 9), N=3.0 * cid, E=-2.0, Alt=alt, Time=5))
    return rows


def test_couas_go_by_alt_is_the_altitude_to_fly_at_not_a_climb() -> None:
    task = load_task_text(json.dumps(psa_shaped_file(10.0)))
    for plan in task.plans:
        assert len(plan.actions) == 15
        # Before the fix every go-by climbed by 10 m: 13 go-bys ended at 140 m.
        assert max(_altitudes(plan.actions)) == 10.0
        assert plan.sync_steps() == [0, 9]
        assert [a.step for a in plan.actions] == list(range(15))  # the file's Steps are kept


def test_couas_go_by_alt_changes_are_relative_to_the_commanded_altitude() -> None:
    rows = [
        couas_row(0, 1, 0, 0, Alt=10),
        couas_row(2, 1, 1, 0, N=5, E=0, Alt=15),
        couas_row(2, 1, 2, 0, N=5, E=0, Alt=15),
        couas_row(1, 1, 3, 0, Lat=47.3978, Lon=8.5456, Alt=20),
        couas_row(2, 1, 4, 0, N=0, E=5, Alt=8),
        couas_row(2, 1, 5, 0, N=0, E=5),  # no Alt: hold altitude
        couas_row(3, 1, 6, 0, Lat=0, Lon=0),
    ]
    (plan,) = load_task_text(json.dumps(rows)).plans
    assert _altitudes(plan.actions) == [10, 15, 15, 20, 8, 8, 0]
    assert [a.up for a in plan.actions if isinstance(a, GoBy)] == [5, 0, -12, 0]


def test_couas_square_at_two_metres_and_single_drone_file() -> None:
    square = [couas_row(0, 1, 0, 0, Alt=2)]
    for step, (n, e) in enumerate([(5, 0), (0, 5), (-5, 0), (0, -5)], start=1):
        square.append(couas_row(2, 1, step, 0, N=n, E=e, Alt=2, Time=0 if step > 1 else 2))
    square.append(couas_row(3, 1, 5, 0, Lat=0, Lon=0))
    (plan,) = load_task_text(json.dumps(square)).plans
    assert len(plan.actions) == 6
    assert _altitudes(plan.actions) == [2, 2, 2, 2, 2, 0]
    assert sum(a.north for a in plan.actions if isinstance(a, GoBy)) == 0


def test_couas_rows_fly_in_file_order_not_step_order() -> None:
    rows = [
        couas_row(0, 1, 0, 0, Alt=10),
        couas_row(2, 1, 5, 0, N=10, E=0, Alt=10),
        couas_row(2, 1, 2, 0, N=0, E=10, Alt=10),
        couas_row(3, 1, 9, 0, Lat=0, Lon=0),
    ]
    (plan,) = load_task_text(json.dumps(rows)).plans
    go_bys = [a for a in plan.actions if isinstance(a, GoBy)]
    assert [(g.north, g.east) for g in go_bys] == [(10, 0), (0, 10)]  # file order
    steps = [a.step for a in plan.actions]
    assert steps == sorted(steps) and len(set(steps)) == len(steps)


def test_couas_syncs_match_by_ordinal_not_by_step_value() -> None:
    # The shape of CoUAS's multiple-drones example: drone 2 has an extra go-to before its
    # second sync, so the drones' k-th syncs carry different Step values.
    rows = [
        couas_row(0, 1, 0, 1, Alt=10),
        couas_row(0, 2, 0, 1, Alt=10),
        couas_row(2, 2, 1, 0, N=6, E=9, Alt=10),
        couas_row(2, 2, 2, 1, N=-5, E=10, Alt=10),
        couas_row(2, 1, 1, 1, N=5, E=10, Alt=10),
        couas_row(2, 2, 3, 1, N=5, E=10, Alt=10),
        couas_row(2, 1, 2, 1, N=5, E=10, Alt=10),
        couas_row(3, 2, 4, 1, Lat=0, Lon=0),
        couas_row(3, 1, 3, 1, Lat=0, Lon=0),
    ]
    one, two = load_task_text(json.dumps(rows)).plans
    assert len(one.actions) == 4 and len(two.actions) == 5
    assert one.sync_steps() == two.sync_steps()
    assert len(one.sync_steps()) == 4
    # Drone 2's first go-by (not a sync) comes before both drones' second sync.
    assert two.actions[1].step < two.actions[2].step == one.actions[1].step


def test_couas_that_never_lands_is_refused_unless_allowed() -> None:
    rows = [couas_row(0, 1, 0, 0, Alt=10)] + [
        couas_row(2, 1, step, int(step % 4 == 0), N=1, E=1, Alt=10) for step in range(1, 9)
    ]
    with pytest.raises(TaskFileError, match=r"row 9 \(CID 1, Step 8\): CID 1 never lands") as info:
        load_task_text(json.dumps(rows))
    assert "allow-airborne-end" in str(info.value)
    task = load_task_text(json.dumps(rows), allow_airborne_end=True)
    assert task.allow_airborne_end
    (warning,) = task_warnings(task)
    assert "cid 1 never land" in warning
    assert task_warnings(load_task_text(json.dumps(COUAS))) == []


def test_fleetgcs_plan_that_never_lands_needs_the_flag() -> None:
    document = {
        "plans": [
            {
                "agent": "a",
                "actions": [
                    {"kind": "takeoff", "step": 0, "alt": 5},
                    {"kind": "goto", "step": 1, "lat": 1, "lon": 1, "alt": 5},
                ],
            }
        ]
    }
    with pytest.raises(TaskFileError, match="a: the last action is not a land or rtl") as info:
        load_task_text(json.dumps(document))
    assert "Value error" not in str(info.value)
    assert load_task_text(json.dumps({**document, "allow_airborne_end": True})).allow_airborne_end
    assert load_task_text(json.dumps(document), allow_airborne_end=True).allow_airborne_end


def test_fleetgcs_task_round_trips_through_json() -> None:
    task = load_task_text(json.dumps(COUAS))
    again = load_task_text(task.model_dump_json())
    assert again == task


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        (
            [couas_row(1, 1, 0, 0, Lat=1, Lon=1, Alt=5)],
            r"row 1 \(CID 1, Step 0\): the first action must be a takeoff, but CID 1 starts with a go-to",
        ),
        (
            [
                couas_row(0, 1, 0, 1, Alt=5),
                couas_row(0, 2, 0, 0, Alt=5),
                couas_row(3, 1, 1, 0),
                couas_row(3, 2, 1, 0),
            ],
            r"unequal sync points: CID 1 has 1 \(rows 1\); CID 2 has 0 \(rows none\)",
        ),
        ([couas_row(0, 1, 0, 0)], r"row 1 \(CID 1, Step 0\): an arm-and-takeoff row lacks 'Alt'"),
        ([couas_row(5, 1, 0, 0, Alt=5)], r"row 1 \(CID 1, Step 0\): Action_type 5 is not one of 0 arm"),
        ([], "non-empty JSON array"),
        (
            [
                couas_row(0, 1, 0, 0, Alt=5),
                couas_row(1, 1, 1, 0, Lat=95, Lon=0, Alt=5),
                couas_row(3, 1, 2, 0),
            ],
            r"row 2 \(CID 1, Step 1\): Lat 95.0, Lon 0.0 is not a position",
        ),
        (
            [
                couas_row(0, 1, 0, 0, Alt=5),
                couas_row(2, 1, 1, 0, N=1, E=1, Alt=5),
                couas_row(2, 1, 0, 0, N=1, E=1, Alt=5),
                couas_row(3, 1, 1, 0),
            ],
            r"rows 1 and 3: CID 1 uses Step 0 twice \(the step numbers restart\)",
        ),
        (
            [couas_row(0, 1, 0, 0, Alt=5), couas_row(2, 1, 1, 0, N=1, E=1, Alt=0), couas_row(3, 1, 2, 0)],
            r"row 2 \(CID 1, Step 1\): Alt 0.0 m; Alt is the altitude to fly at",
        ),
        ([{"CID": 1, "Step": 0}], "CoUAS row 1: Action_type: Field required"),
        (
            [couas_row(0, 1, 0, 0, Alt=5), couas_row(2, 1, 1, 0, N=1e9, E=1, Alt=5), couas_row(3, 1, 2, 0)],
            r"row 2 \(CID 1, Step 1\): north: Input should be less than or equal to 100000",
        ),
    ],
)
def test_invalid_couas_files_are_rejected_with_reasons(rows: list[dict[str, float]], message: str) -> None:
    with pytest.raises(TaskFileError, match=message) as info:
        load_task_text(json.dumps(rows))
    assert "Value error" not in str(info.value)


# Published pairs (WGS-84 lat, lon -> GCJ-02 lat, lon) used by the eviltransform libraries' tests.
GCJ_PAIRS = [
    ((31.1774276, 121.5272106), (31.17530398364597, 121.531541859215)),  # Shanghai
    ((22.543847, 113.912316), (22.540796131694766, 113.9171764808363)),  # Shenzhen
    ((39.911954, 116.377817), (39.91334545536069, 116.38404722455657)),  # Beijing
]


@pytest.mark.parametrize(("wgs", "gcj"), GCJ_PAIRS)
def test_gcj02_transform_matches_published_pairs(wgs: tuple[float, float], gcj: tuple[float, float]) -> None:
    assert wgs84_to_gcj02(*wgs) == pytest.approx(gcj, abs=1e-9)
    back = gcj02_to_wgs84(*gcj)
    assert distance_m(*back, *wgs) < 0.01  # the iterative inverse is good to a centimetre
    assert distance_m(*wgs, *gcj) > 100  # and the offset it removes is hundreds of metres


def test_gcj02_is_identity_outside_china_and_an_import_option() -> None:
    assert gcj02_to_wgs84(47.3977, 8.5456) == (47.3977, 8.5456)
    (wgs, gcj) = GCJ_PAIRS[0]
    rows = [
        couas_row(0, 1, 0, 0, Alt=10),
        couas_row(1, 1, 1, 0, Lat=gcj[0], Lon=gcj[1], Alt=10),
        couas_row(3, 1, 2, 0, Lat=gcj[0], Lon=gcj[1]),
    ]
    (raw,) = load_task_text(json.dumps(rows)).plans
    (converted,) = load_task_text(json.dumps(rows), gcj02=True).plans
    assert (raw.actions[1].lat, raw.actions[1].lon) == gcj
    for action in converted.actions[1:]:
        assert distance_m(action.lat, action.lon, *wgs) < 0.01


def test_steps_must_not_go_backwards() -> None:
    document = {
        "plans": [
            {
                "agent": "a",
                "actions": [
                    {"kind": "takeoff", "step": 0, "alt": 5},
                    {"kind": "goto", "step": 3, "lat": 1, "lon": 1, "alt": 5},
                    {"kind": "land", "step": 2},
                ],
            }
        ]
    }
    with pytest.raises(TaskFileError, match="step 2 after step 3"):
        load_task_text(json.dumps(document))


def test_plan_needs_exactly_one_address_and_unique_agents() -> None:
    takeoff = {"kind": "takeoff", "step": 0, "alt": 5}
    with pytest.raises(TaskFileError, match="exactly one of 'agent'"):
        load_task_text(json.dumps({"plans": [{"agent": "a", "cid": 1, "actions": [takeoff]}]}))
    with pytest.raises(TaskFileError, match="more than one plan"):
        load_task_text(json.dumps({"plans": [{"agent": "a", "actions": [takeoff]}] * 2}))


def test_not_json_is_a_clear_error() -> None:
    with pytest.raises(TaskFileError, match="not JSON"):
        load_task_text("{plans: nope")


def test_schema_is_published() -> None:
    schema = TaskFile.model_json_schema()
    assert schema["properties"]["format"]["const"] == "fleetgcs-task"


def test_a_stored_task_without_landing_still_loads_but_submission_refuses_it() -> None:
    # Missions stored by older versions are re-read with model_validate_json on restart; the
    # landing rule applies where documents come in (the API, gcs run), not to stored ones.
    takeoff = {"kind": "takeoff", "step": 0, "alt": 5}
    stored = TaskFile.model_validate({"plans": [{"agent": "a", "actions": [takeoff]}]})
    assert stored.allow_airborne_end is False
    with pytest.raises(TaskFileError, match="a: the last action is not a land or rtl"):
        load_task_text(stored.model_dump_json())
