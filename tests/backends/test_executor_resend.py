"""The executor re-sends a position target only while the vehicle does not fly to it (issue 26).

On PX4 every DO_REPOSITION is a switch to Hold: a re-send in the second between a pilot's mode switch
and the heartbeat that shows it took the vehicle back from the pilot (seen on real PX4, 2 flights in 5,
tests/px4/test_field.py). A target the vehicle does not fly to (lost, or dropped by PX4 at the end of
a take-off) is still re-sent.
"""

from __future__ import annotations

import asyncio

from agent.autopilot.memory import MemoryAutopilot
from agent.config import AgentConfig
from agent.executor import ActionExecutor
from protocol.actions import Goto
from protocol.geo import offset_latlon

HOME = (47.397742, 8.545594, 488.0)


class CountingAutopilot(MemoryAutopilot):
    """Counts gotos; the first ``lose`` of them never reach the vehicle (a lossy link)."""

    def __init__(self, lose: int = 0) -> None:
        super().__init__(HOME, speed_mps=5.0, speedup=10.0)
        self.gotos = 0
        self.lose = lose

    async def goto(self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None = None) -> None:
        self.gotos += 1
        if self.gotos <= self.lose:
            return
        await super().goto(lat, lon, alt_rel_m, speed_mps)


async def _fly(ap: CountingAutopilot) -> None:
    config = AgentConfig(identity="resend", key_hex="00" * 32, resend_target_s=0.3)
    await ap.connect()
    try:
        await ap.arm()
        await ap.takeoff(10.0)
        for _ in range(200):  # bounded: 10 s
            if ap.telemetry().alt_rel >= 9.9:
                break
            await asyncio.sleep(0.05)
        lat, lon = offset_latlon(HOME[0], HOME[1], 60.0, 0.0)
        await asyncio.wait_for(ActionExecutor(ap, config).run(Goto(step=0, lat=lat, lon=lon, alt=10.0)), 20.0)
    finally:
        await ap.close()


async def test_a_target_the_vehicle_flies_to_is_not_sent_again() -> None:
    ap = CountingAutopilot()
    await _fly(ap)  # 60 m at 5 m/s, 10x: about 1.2 s of wall time, four re-send periods
    assert ap.gotos == 1


async def test_a_lost_target_is_sent_again() -> None:
    ap = CountingAutopilot(lose=1)
    await _fly(ap)
    assert ap.gotos == 2
