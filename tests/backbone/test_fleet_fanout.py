"""A fleet-wide safety order goes out in one pass (issue 29): every drone's return order is on its
link before any of the ~2 events a drone is recorded with, the events are all stored after (one
transaction), and every agent gets its order. Real daemon, real protocol clients on loopback."""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path

import pytest

from gcs.cooperation.returns import RETURN_PREFIX
from gcs.observe.events import EventBus
from gcs.storage.store import Store
from protocol.geo import offset_latlon
from protocol.packets import Battery, Gps, PerformActions, Position, StatusReport
from protocol.session import ClientHandshake
from protocol.stream import FramedStream, open_client
from tests.backbone.helpers import HOME, new_key, running_daemon, wait_for

pytestmark = pytest.mark.timeout(120)
FLEET = 24


def _airborne(index: int) -> StatusReport:
    lat, lon = offset_latlon(HOME[0], HOME[1], 40.0 * (index // 6), 40.0 * (index % 6))
    return StatusReport(
        time=time.time(),
        position=Position(lat=lat, lon=lon, alt_rel=12.0, alt_amsl=HOME[2] + 12.0),
        battery=Battery(pct=80.0, voltage_v=12.0, current_a=10.0),
        gps=Gps(fix=3, satellites=14),
        mode="GUIDED",
        armed=True,
        landed=False,
    )


async def _return_order(stream: FramedStream, timeout: float) -> PerformActions:
    """The first return program the daemon sends this client (bounded by ``timeout``)."""
    deadline = time.monotonic() + timeout
    for _ in range(1000):
        frame = await stream.read_frame(timeout=max(0.01, deadline - time.monotonic()))
        body = frame.body
        if isinstance(body, PerformActions) and body.mission_id.startswith(RETURN_PREFIX):
            return body
    raise AssertionError("no return order among 1000 frames")


async def test_fleet_rtl_orders_every_drone_before_recording_any(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        streams: list[FramedStream] = []
        try:
            for i in range(FLEET):
                stream, _ = await open_client(
                    "127.0.0.1", daemon.listen_port, ClientHandshake(f"d{i}", bytes.fromhex(key)), timeout=5.0
                )
                streams.append(stream)
                await stream.send(_airborne(i))
            await wait_for(
                lambda: all((s := daemon.agents.session(f"d{i}")) and s.status for i in range(FLEET)),
                10,
                "every drone's status",
            )
            sessions = [daemon.agents.session(f"d{i}") for i in range(FLEET)]
            written_before = [s.outbox.written for s in sessions if s is not None]
            written_at_first_record: list[int] = []
            add_event = daemon.store.add_event

            def add_event_and_count(*args: object, **kwargs: object) -> object:
                if not written_at_first_record and args[0] in ("command", "return_planned"):
                    written = [s.outbox.written for s in sessions if s is not None]
                    written_at_first_record.append(
                        sum(now > before for now, before in zip(written, written_before, strict=True))
                    )
                return add_event(*args, **kwargs)  # type: ignore[arg-type]

            daemon.store.add_event = add_event_and_count  # type: ignore[method-assign,assignment]
            delivered, _ = await daemon.operator.bring_down("rtl", None, "test")
            assert sorted(delivered) == sorted(f"d{i}" for i in range(FLEET))
            # Every drone's order was handed to its socket before the first of its records.
            assert written_at_first_record == [FLEET]
            orders = await asyncio.gather(*(_return_order(s, 10.0) for s in streams))
            assert {o.source for o in orders} == {"operator"} and all(o.mode == "replace" for o in orders)
            planned = daemon.events.history(kind="return_planned", limit=10_000)
            commands = daemon.events.history(kind="command", limit=10_000)
            assert len(planned) == FLEET and len(commands) >= FLEET
            assert all(e.id > 0 for e in planned)
        finally:
            for stream in streams:
                with contextlib.suppress(Exception):
                    await stream.close()


async def test_deferred_events_are_stored_at_the_end_in_order_with_their_times(tmp_path: Path) -> None:
    store = Store(tmp_path / "fleet.db")
    try:
        bus = EventBus(store)
        queue = bus.subscribe()
        with bus.deferred():
            first = bus.publish("one", "first", agent="d1")
            with bus.deferred():  # nested: still the outer block's
                bus.publish("two", "second", data={"n": 2})
            assert store.events() == [] and queue.empty()  # nothing stored or handed out yet
        assert first.id == 0
        stored = store.events()
        assert [(e.kind, e.message, e.agent, e.data) for e in stored] == [
            ("one", "first", "d1", {}),
            ("two", "second", None, {"n": 2}),
        ]
        assert stored[0].time == first.time and stored[0].id < stored[1].id
        handed = [queue.get_nowait(), queue.get_nowait()]
        assert [e.id for e in handed] == [e.id for e in stored]
        bus.publish("three", "at once")  # outside a block: stored when published
        assert store.events()[-1].kind == "three"
    finally:
        store.close()
