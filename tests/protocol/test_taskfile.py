"""Task files: the fleetgcs format, CoUAS import, and the validation that prevents barrier deadlocks."""

from __future__ import annotations

import json

import pytest

from protocol.actions import GoBy, Goto, Land, Takeoff
from protocol.taskfile import TaskFile, TaskFileError, load_task_text


def couas_row(action_type: int, cid: int, step: int, sync: int, **fields: float) -> dict[str, float | int]:
    return {"Action_type": action_type, "CID": cid, "Step": step, "Sync": sync, **fields}


COUAS = [
    couas_row(0, 1, 0, 1, Alt=10),
    couas_row(0, 2, 0, 1, Alt=12),
    couas_row(1, 1, 1, 1, Lat=47.3978, Lon=8.5456, Alt=10),
    couas_row(2, 2, 1, 1, N=10, E=-5, Alt=0),
    couas_row(3, 1, 2, 0, Lat=0, Lon=0),
    couas_row(3, 2, 2, 0, Lat=47.3977, Lon=8.5457, Time=3.5),
]


def test_couas_file_converts_per_cid_in_step_order() -> None:
    shuffled = list(reversed(COUAS))
    task = load_task_text(json.dumps(shuffled))
    assert [p.cid for p in task.plans] == [1, 2]
    one, two = task.plans
    assert [type(a) for a in one.actions] == [Takeoff, Goto, Land]
    assert [type(a) for a in two.actions] == [Takeoff, GoBy, Land]
    assert one.actions[2] == Land(step=2)  # 0,0 means "land here"
    assert two.actions[2] == Land(step=2, lat=47.3977, lon=8.5457)
    assert two.actions[1] == GoBy(step=1, sync=True, north=10, east=-5, up=0)
    assert one.sync_steps() == two.sync_steps() == [0, 1]


def test_fleetgcs_task_round_trips_through_json() -> None:
    task = load_task_text(json.dumps(COUAS))
    again = load_task_text(task.model_dump_json())
    assert again == task


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ([couas_row(1, 1, 0, 0, Lat=1, Lon=1, Alt=5)], "first action must be a takeoff"),
        ([couas_row(0, 1, 0, 1, Alt=5), couas_row(0, 2, 0, 0, Alt=5)], "unequal sync points"),
        ([couas_row(0, 1, 0, 0)], "lacks 'Alt'"),
        ([couas_row(5, 1, 0, 0, Alt=5)], "CoUAS row 0: Action_type"),
        ([], "non-empty JSON array"),
        (
            [couas_row(0, 1, 0, 0, Alt=5), couas_row(1, 1, 1, 0, Lat=95, Lon=0, Alt=5)],
            "less than or equal to 90",
        ),
    ],
)
def test_invalid_couas_files_are_rejected_with_reasons(rows: list[dict[str, float]], message: str) -> None:
    with pytest.raises(TaskFileError, match=message):
        load_task_text(json.dumps(rows))


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
