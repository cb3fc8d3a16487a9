"""Shared pieces of the link-layer tests: a peer that stops reading, timing at a real agent."""

from __future__ import annotations

import asyncio
import math
import time

from gcs.core.daemon import Daemon
from protocol.packets import FenceVertex, Geofence, PerformActions, SetParameters
from tests.backbone.helpers import RunningAgent

BIG_FENCE = SetParameters(
    geofence=Geofence(
        polygon=[
            FenceVertex(lat=47.0 + 0.001 * math.sin(i / 80), lon=8.0 + 0.001 * math.cos(i / 80))
            for i in range(500)
        ]
    )
)  # about 25 KB on the wire


async def stall_outbox(daemon: Daemon, identity: str, frames_waiting: int = 3, limit: int = 2000) -> int:
    """Post big frames to a peer that does not read until ``frames_waiting`` wait in its outbox.

    Returns how many were posted. Bounded: socket buffers fill long before ``limit`` frames.
    """
    session = daemon.agents.session(identity)
    assert session is not None
    for posted in range(1, limit + 1):
        assert daemon.agents.post(identity, BIG_FENCE), f"{identity} was cut off while filling"
        await asyncio.sleep(0.002)
        if session.outbox.queued >= frames_waiting:
            return posted
    raise AssertionError(f"{identity}'s outbox never backed up after {limit} frames")


def record_actions(running: RunningAgent) -> list[tuple[float, PerformActions]]:
    """(monotonic receive time, packet) of every type-4 packet the agent's link hands over."""
    seen: list[tuple[float, PerformActions]] = []
    link = running.agent.link
    original = link._on_actions

    async def on_actions(packet: PerformActions) -> None:
        seen.append((time.monotonic(), packet))
        await original(packet)

    link._on_actions = on_actions  # type: ignore[method-assign]
    return seen
