"""Two drones on a head-on course are kept apart by the daemon, and the mission still completes."""

from __future__ import annotations

from pathlib import Path

from gcs.cooperation.config import CooperationConfig, EnergyConfig
from gcs.cooperation.flightlog import summarize
from tests.cooperation.rig import SPEEDUP, assert_pair_separated, head_on_task, rig, wait_for


async def test_head_on_pair_is_held_apart_and_the_mission_completes(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    coop = CooperationConfig(
        vehicle_time_scale=SPEEDUP, energy=EnergyConfig(record_dir=logs, record_time_scale=SPEEDUP)
    )
    async with rig(tmp_path, 2, coop) as r:
        mission_id = await r.daemon.missions.submit(head_on_task())
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 60, "mission end")
        progress = r.daemon.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed", progress
        await wait_for(lambda: all(r.landed(n) for n in r.names), 30, "both landed")

        holds = r.events("collision_hold")
        escapes = r.events("collision_escape")
        assert escapes and escapes[0].agent == "drone-2", [e.message for e in escapes]  # higher CID yields
        assert any(e.agent == "drone-1" for e in holds)  # drone-1 waited while drone-2 climbed clear
        assert any(e.agent == "drone-2" for e in holds)  # then drone-2 held while drone-1 passed
        assert r.events("collision_release")
        assert not r.daemon.missions.active
        assert not any(r.daemon.authority.is_held(n) for n in r.names)  # nobody left paused

        # Ground truth from the simulator: never inside a 2 m x 1 m bubble of each other in the air.
        assert assert_pair_separated(r.truth) > 2.0

        # The service recorded each drone-flight as a flight log the energy trainer reads.
        csvs = sorted(logs.glob("*.csv"))
        assert len(csvs) == 2
        for path in csvs:
            flight = summarize(path)
            assert flight.time_s > 20.0 and flight.distance_m > 80.0 and flight.energy_wh > 0.5
            assert path.with_suffix(".plan.json").exists()
