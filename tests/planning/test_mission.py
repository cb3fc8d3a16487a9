import json

import pytest

from gcs.planning.mission import mission_from_paths
from protocol.actions import Goto, Hold, Land, ReturnToLaunch, Takeoff, Waypoints
from protocol.taskfile import TaskFile, load_task_text


def test_mission_shape_validates_and_round_trips():
    paths = [[(47.0, 8.0), (47.001, 8.0)], [(47.0, 8.001)] * 4500, []]
    tf = mission_from_paths(paths, 30.0, 4.0, ["a", "b", "c"], transit_alt_step=5.0)
    assert isinstance(tf, TaskFile)
    syncs = [p.sync_steps() for p in tf.plans]
    assert syncs[0] == syncs[1] == syncs[2] == [0, 4]
    a, b, c = (p.actions for p in tf.plans)
    assert isinstance(a[0], Takeoff) and a[0].alt == 30 and b[0].alt == 35 and c[0].alt == 40
    assert isinstance(a[1], Goto) and (a[1].lat, a[1].lon) == (47.0, 8.0)
    assert [len(x.points) for x in b if isinstance(x, Waypoints)] == [2000, 2000, 500]
    assert isinstance(c[1], Hold) and c[1].sync
    assert all(isinstance(p.actions[-1], ReturnToLaunch) for p in tf.plans)
    text = tf.model_dump_json()
    assert load_task_text(text) == tf
    assert json.loads(text)["format"] == "fleetgcs-task"


def test_land_home_and_cids():
    tf = mission_from_paths(
        [[(1.0, 2.0)]], 20.0, cids=[7], homes_latlon=[(1.1, 2.1)], return_mode="land_home"
    )
    acts = tf.plans[0].actions
    assert tf.plans[0].cid == 7
    assert isinstance(acts[-2], Goto) and isinstance(acts[-1], Land) and acts[-1].lat == 1.1


def test_bad_inputs():
    with pytest.raises(ValueError):
        mission_from_paths([], 20.0)
    with pytest.raises(ValueError):
        mission_from_paths([[(1.0, 2.0)]], 20.0, ["a", "b"])
    with pytest.raises(ValueError):
        mission_from_paths([[(1.0, 2.0)]], 20.0, return_mode="land_home")
