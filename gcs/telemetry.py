"""Telemetry logging: every agent's status reports into the daemon's SQLite file, and flight logs out.

Samples are batched and written every ``flush_s`` (one transaction per batch, not one per
report), optionally downsampled to one per ``period_s`` per agent, and pruned after
``retention_s``. A daemon killed with ``kill -9`` loses at most the last ``flush_s`` of
samples. Steps, sync releases, missions and events are written at once, not batched.

Flight logs: CSV (one row per sample, the columns of :data:`CSV_COLUMNS`) and GeoJSON (one
LineString per flight), with flights split at each arm...landed-and-disarmed cycle.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import io
import json
import logging
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from gcs.agents import AgentSession
from gcs.config import TelemetryConfig
from gcs.store import Store
from protocol.packets import StatusReport

if TYPE_CHECKING:
    from gcs.daemon import Daemon

log = logging.getLogger("gcs.telemetry")

CSV_COLUMNS = (
    "time", "gps_fix", "satellites", "lat", "lon", "alt_rel", "alt_amsl", "vn", "ve", "vd", "heading_deg",
    "battery_pct", "voltage_v", "current_a", "mode", "armed", "landed", "step", "mission_id",
)  # fmt: skip
# gps_fix is the GPS fix type (0-1 none, 2 2D, 3 3D, 4 DGPS, 5 RTK float, 6 RTK fixed): a position
# without a 3D fix is not a place the vehicle was, so readers can drop or flag those rows.


def status_row(agent: str, status: StatusReport, received: float) -> tuple[Any, ...]:
    """One telemetry row in ``gcs.store.TELEMETRY_COLUMNS`` order."""
    p, v, b = status.position, status.velocity, status.battery
    return (
        agent, status.time, received, p.lat, p.lon, p.alt_rel, p.alt_amsl, v.vn, v.ve, v.vd,
        status.heading_deg, b.pct, b.voltage_v, b.current_a, status.mode, int(status.armed),
        int(status.landed), status.gps.fix, status.gps.satellites, status.step, status.mission_id,
        int(status.buffered),
    )  # fmt: skip


class TelemetryRecorder:
    """A daemon service: logs status reports to the store in batches."""

    name = "telemetry"

    def __init__(self, config: TelemetryConfig) -> None:
        self.config = config
        self._store: Store | None = None
        self._batch: list[tuple[Any, ...]] = []
        self._last_kept: dict[str, float] = {}
        self._task: asyncio.Task[None] | None = None
        self.written = 0

    async def start(self, daemon: Daemon) -> None:
        if not self.config.enabled:
            return
        self._store = daemon.store
        daemon.agents.on_status.append(self._on_status)
        self._task = asyncio.create_task(self._run(), name="telemetry-writer")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self.flush()

    async def _on_status(self, session: AgentSession, status: StatusReport) -> None:
        if self.config.period_s > 0:
            last = self._last_kept.get(session.identity)
            if last is not None and 0 <= status.time - last < self.config.period_s:
                return
            self._last_kept[session.identity] = status.time
        self._batch.append(status_row(session.identity, status, time.time()))

    def flush(self) -> None:
        if self._store is None or not self._batch:
            return
        batch, self._batch = self._batch, []
        self._store.add_telemetry(batch)
        self.written += len(batch)

    def history(self, identity: str, since: float = 0.0, limit: int = 1000) -> list[dict[str, Any]]:
        """Logged samples of ``identity`` since ``since`` (agent time), pending batch included."""
        self.flush()
        if self._store is None:
            return []
        return self._store.telemetry(identity, since, limit=limit)

    async def _run(self) -> None:
        last_prune = 0.0
        while True:
            await asyncio.sleep(self.config.flush_s)
            self.flush()
            now = time.monotonic()
            if now - last_prune >= self.config.prune_every_s and self._store is not None:
                last_prune = now
                removed = self._store.prune_telemetry(time.time() - self.config.retention_s)
                if removed:
                    log.info(
                        "pruned %d telemetry samples older than %.0f s", removed, self.config.retention_s
                    )


def split_flights(samples: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """Cut a sample list into flights: from arming to being landed and disarmed again."""
    flights: list[list[dict[str, Any]]] = []
    current: list[dict[str, Any]] = []
    for sample in samples:
        if sample["armed"]:
            current.append(sample)
        elif current:
            current.append(sample)  # the landed-and-disarmed sample closes the flight
            flights.append(current)
            current = []
    if current:
        flights.append(current)
    return flights


def to_csv(samples: Iterable[dict[str, Any]]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for s in samples:
        writer.writerow(["" if s[c] is None else s[c] for c in CSV_COLUMNS])
    return out.getvalue()


def to_geojson(agent: str, flights: list[list[dict[str, Any]]]) -> dict[str, Any]:
    features = []
    for index, flight in enumerate(flights):
        fixed = [s for s in flight if s["gps_fix"] >= 3 and s["lat"] is not None]
        coordinates = [[s["lon"], s["lat"], s["alt_rel"]] for s in fixed]
        if len(coordinates) < 2:
            continue
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "LineString", "coordinates": coordinates},
                "properties": {
                    "agent": agent,
                    "flight": index,
                    "start": flight[0]["time"],
                    "end": flight[-1]["time"],
                    "missions": sorted({s["mission_id"] for s in flight if s["mission_id"]}),
                    "gps_fix": [s["gps_fix"] for s in fixed],  # one per coordinate
                    "samples_without_3d_fix": len(flight) - len(fixed),
                },
            }
        )
    return {"type": "FeatureCollection", "features": features}


def to_geojson_text(agent: str, flights: list[list[dict[str, Any]]]) -> str:
    return json.dumps(to_geojson(agent, flights), indent=1)
