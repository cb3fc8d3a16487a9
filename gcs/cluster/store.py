"""The daemon's store when it runs in a cluster: shared records in JetStream, the rest local.

Agents, CIDs, missions, progress, barrier releases and operator holds come from and go to the
shared buckets (:class:`gcs.cluster.state.ClusterState`); events are kept in the local SQLite file
as before (the API pages them from there) and also appended to the shared event stream;
telemetry stays local (the shared copy is the FLEET_TELEMETRY stream).
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

from gcs.cluster.state import ClusterState
from gcs.storage.store import Store, StoredEvent, StoredMission


class ClusterStore(Store):
    def __init__(self, path: Path | str, state: ClusterState) -> None:
        super().__init__(path)
        self.state = state

    # --- agents ---------------------------------------------------------------------------------

    def cid_for(self, identity: str, capabilities: dict[str, Any]) -> int:
        """Registered CID (assigned with :meth:`ClusterState.assign_cid` during the handshake)."""
        record = self.state.agent_record(identity)
        if record is None:
            raise RuntimeError(f"{identity} has no CID in the cluster registry yet")
        return int(record["cid"])

    def identity_for_cid(self, cid: int) -> str | None:
        raw = self.state.mirror["cids"].get(f"c{cid}")
        return None if raw is None else raw.decode().split(" ", 1)[0]

    def known_agents(self) -> dict[str, int]:
        return {k: int(v["cid"]) for k, v in self.state.json_values("agents").items()}

    # --- missions -------------------------------------------------------------------------------

    def _mission_record(self, mission_id: str) -> dict[str, Any] | None:
        raw = self.state.mirror["missions"].get(mission_id)
        return None if raw is None else json.loads(raw)

    def add_mission(self, mission_id: str, name: str, task_json: str, agents: list[str]) -> None:
        record = {
            "id": mission_id,
            "name": name,
            "task": task_json,
            "state": "running",
            "created": time.time(),
            "finished": None,
            "result": None,
            "paused": False,
            "leader": self.state.daemon_id,
        }
        leases = self.state.leases
        taking = leases.pending[mission_id] = asyncio.Event()  # its records get this take's token

        async def lead() -> None:  # the submitting daemon leads
            await self.state.take_lease(mission_id)
            leases.pending.pop(mission_id, None)
            taking.set()

        self.state.enqueue(lead)
        self.state.put_fenced("missions", mission_id, record, mission_id)
        for agent in agents:
            progress = {"completed": -1, "excluded": False}
            self.state.put_fenced("progress", f"{mission_id}.{agent}", progress, mission_id)

    def _update_mission(self, mission_id: str, **changes: Any) -> None:
        record = self._mission_record(mission_id)
        if record is not None:
            record.update(changes)
            self.state.put_fenced("missions", mission_id, record, mission_id)  # the leader's, fenced

    def finish_mission(self, mission_id: str, state: str, result: str) -> None:
        self._update_mission(mission_id, state=state, finished=time.time(), result=result, paused=False)

    def mission(self, mission_id: str) -> StoredMission | None:
        record = self._mission_record(mission_id)
        return None if record is None else _stored(record)

    def missions(self, state: str | None = None) -> list[StoredMission]:
        records = [json.loads(v) for v in list(self.state.mirror["missions"].values())]
        chosen = [r for r in records if state is None or r["state"] == state]
        return [_stored(r) for r in sorted(chosen, key=lambda r: r["created"])]

    def set_paused(self, mission_id: str, paused: bool) -> None:
        self._update_mission(mission_id, paused=paused)

    def paused_missions(self) -> set[str]:
        return {
            k
            for k, r in self.state.json_values("missions").items()
            if r["paused"] and r["state"] == "running"
        }

    def save_hold(self, agent: str, owner: str, reason: str) -> None:
        self.state.put_json("holds", f"{agent}.{owner}", {"agent": agent, "owner": owner, "reason": reason})

    def drop_hold(self, agent: str, owner: str) -> None:
        self.state.delete("holds", f"{agent}.{owner}")

    def holds(self) -> list[tuple[str, str, str]]:
        return [(h["agent"], h["owner"], h["reason"]) for h in self.state.json_values("holds").values()]

    def set_completed_step(self, mission_id: str, agent: str, step: int) -> None:
        key = f"{mission_id}.{agent}"
        record = self.state.json_values("progress", key).get(key) or {"completed": -1, "excluded": False}
        if step > record["completed"]:
            self.state.put_fenced("progress", key, {**record, "completed": step}, mission_id)

    def exclude_agent(self, mission_id: str, agent: str) -> None:
        key = f"{mission_id}.{agent}"
        record = self.state.json_values("progress", key).get(key) or {"completed": -1, "excluded": False}
        self.state.put_fenced("progress", key, {**record, "excluded": True}, mission_id)

    def mission_agents(self, mission_id: str) -> dict[str, tuple[int, bool]]:
        prefix = f"{mission_id}."
        return {
            k[len(prefix) :]: (int(v["completed"]), bool(v["excluded"]))
            for k, v in self.state.json_values("progress", prefix).items()
        }

    def journal_release(self, mission_id: str, step: int) -> float:
        """Nothing to journal: the compare-and-set claim in shared state (:meth:`ClusterState.create`)
        made the release durable before the runner sends it."""
        return time.time()

    def recover_releases(self) -> list[tuple[str, int]]:
        """Releases live in shared state, never journaled here (see :meth:`journal_release`)."""
        return []

    def record_release(self, mission_id: str, step: int, at: float | None = None) -> None:
        """Already written by the compare-and-set claim (:meth:`ClusterState.create`); mirror only."""
        self.state.mirror["barriers"].setdefault(f"{mission_id}.{step}.released", b"%f" % time.time())

    def released_steps(self, mission_id: str) -> set[int]:
        prefix = f"{mission_id}."
        steps = set()
        for key in list(self.state.mirror["barriers"]):
            parts = key[len(prefix) :].split(".")
            if key.startswith(prefix) and len(parts) == 2 and parts[1] == "released" and parts[0].isdigit():
                steps.add(int(parts[0]))
        return steps

    def arrivals(self, mission_id: str) -> dict[int, set[str]]:
        """Recorded barrier arrivals of a mission: step -> agents."""
        prefix = f"{mission_id}."
        found: dict[int, set[str]] = {}
        for key in list(self.state.mirror["barriers"]):
            if not key.startswith(prefix):
                continue
            step, _, rest = key[len(prefix) :].partition(".")
            kind, _, agent = rest.partition(".")
            if kind == "arrived" and step.isdigit() and agent:
                found.setdefault(int(step), set()).add(agent)
        return found

    # --- events ---------------------------------------------------------------------------------

    def add_event(
        self,
        kind: str,
        severity: str,
        message: str,
        agent: str | None = None,
        mission_id: str | None = None,
        data: dict[str, Any] | None = None,
        at: float | None = None,
    ) -> StoredEvent:
        stored = super().add_event(kind, severity, message, agent, mission_id, data, at)
        payload = {
            "daemon": self.state.daemon_id,
            "time": stored.time,
            "kind": kind,
            "severity": severity,
            "agent": agent,
            "mission_id": mission_id,
            "message": message,
            "data": stored.data,
        }
        self.state.publish(f"fleet.events.{self.state.daemon_id}", json.dumps(payload, default=str).encode())
        return stored


def _stored(record: dict[str, Any]) -> StoredMission:
    return StoredMission(
        record["id"],
        record["name"],
        record["task"],
        record["state"],
        record["created"],
        record["finished"],
        record["result"],
    )
