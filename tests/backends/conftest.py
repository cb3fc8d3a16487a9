"""Fixtures for backend tests: a real simulator fleet on loopback TCP and bounded waits."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any

import pytest

from agent.autopilot.base import Autopilot, Telemetry

HOME = (47.397742, 8.545594, 488.0)
SPEEDUP = 20.0


def fleet_config(**overrides: Any) -> Any:
    from sitl.fleet import FleetConfig

    options: dict[str, Any] = {
        "vehicles": 1,
        "home": HOME,
        "base_port": 0,
        "speedup": SPEEDUP,
        "seed": 1,
        "transport": "tcp",
        "spacing_m": 5.0,
        "prearm_delay_s": 3.0,
        "legacy_mission_request": False,
        "wind": (0.0, 0.0),
        "gust_mps": 0.0,
    }
    options.update(overrides)
    return FleetConfig(**options)


@pytest.fixture
def sim_fleet() -> Iterator[Callable[..., Any]]:
    """``sim_fleet(**config_overrides)`` starts a SimFleet that is stopped after the test."""
    from sitl.fleet import SimFleet

    started: list[Any] = []

    def start(**overrides: Any) -> Any:
        fleet = SimFleet(fleet_config(**overrides))
        fleet.__enter__()
        started.append(fleet)
        return fleet

    yield start
    for fleet in reversed(started):
        fleet.__exit__(None, None, None)


@pytest.fixture
async def closing() -> AsyncIterator[Callable[[Autopilot], Autopilot]]:
    """Register autopilots to be closed at the end of the test."""
    opened: list[Autopilot] = []

    def add(ap: Autopilot) -> Autopilot:
        opened.append(ap)
        return ap

    yield add
    for ap in reversed(opened):
        await ap.close()


async def wait_until(
    ap: Autopilot, predicate: Callable[[Telemetry], bool], what: str, timeout: float = 10.0
) -> Telemetry:
    """Poll telemetry until ``predicate`` holds; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        tel = ap.telemetry()
        if predicate(tel):
            return tel
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}; last telemetry {tel}")
        await asyncio.sleep(0.02)
