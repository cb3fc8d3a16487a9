"""Flight logs for energy-model training: one CSV per flight, with a plan sidecar.

Not :class:`gcs.observe.flight_recorder.FlightRecorder`, which keeps per-flight figures in memory for
the demo's summary; this one writes the files ``gcs energy fit`` learns from.
"""

from __future__ import annotations

import json
from pathlib import Path

from gcs.cooperation.config import EnergyConfig
from gcs.cooperation.energy import estimate_mission
from gcs.cooperation.flightlog import FlightLogWriter
from gcs.cooperation.preflight import StartPoints
from gcs.cooperation.tracking import TrackedAgent
from protocol.actions import Action
from protocol.packets import StatusReport


class EnergyLogRecorder:
    """Starts a log when a drone arms and closes it when it lands disarmed (``energy.record_dir``)."""

    def __init__(self, config: EnergyConfig) -> None:
        self.config = config
        self._recordings = 0

    def record(
        self,
        agent: TrackedAgent,
        status: StatusReport,
        mission: tuple[str, dict[str, list[Action]]] | None,
        homes: StartPoints,
    ) -> None:
        directory = self.config.record_dir
        if directory is None:
            return
        if agent.recorder is None and status.armed:
            self._recordings += 1
            name = f"{status.mission_id or 'none'}_{agent.ident}_{self._recordings}"
            agent.recorder = FlightLogWriter(Path(directory) / f"{name}.csv", self.config.record_time_scale)
            self._write_plan_sidecar(agent, Path(directory) / f"{name}.plan.json", mission, homes)
        if agent.recorder is not None:
            agent.recorder.add(status)
            if status.landed and not status.armed:
                agent.recorder.close()
                agent.recorder = None

    def _write_plan_sidecar(
        self,
        agent: TrackedAgent,
        path: Path,
        mission: tuple[str, dict[str, list[Action]]] | None,
        homes: StartPoints,
    ) -> None:
        if mission is None or agent.ident not in mission[1]:
            return
        mission_id, plans = mission
        if set(homes) != set(plans):
            return
        estimate = estimate_mission(plans, homes, self.config)[agent.ident]
        payload = {
            "agent": agent.ident,
            "mission_id": mission_id,
            "home": list(homes[agent.ident]),
            "planned": [round(v, 3) for v in estimate],
            "actions": [a.model_dump(exclude_none=True) for a in plans[agent.ident]],
        }
        path.write_text(json.dumps(payload))
