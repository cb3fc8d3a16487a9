"""`gcs cluster up` end to end: a real process starting a 3-node NATS JetStream cluster and two
daemons on loopback; both APIs answer as members of one cluster, the shared buckets are replicated
on all three NATS servers, and SIGINT (a terminal's Ctrl-C) stops every child process and
removes the temporary directory. Every wait is bounded; whatever is left is killed on the way out.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import httpx
import nats
import pytest

from gcs.cluster.natsrun import missing_reason
from tests.support.processes import BIN

pytestmark = pytest.mark.slow


def _alive(pid: int) -> bool:
    """Running (a zombie, dead but not yet reaped, is not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


async def _ready(process: subprocess.Popen[bytes], ready: Path, log: Path) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if ready.exists() and ready.read_text().strip():
            return dict(json.loads(ready.read_text()))
        assert process.poll() is None, f"gcs cluster up exited: {log.read_text()[-2000:]}"
        await asyncio.sleep(0.1)
    raise AssertionError(f"gcs cluster up not ready in 60 s: {log.read_text()[-2000:]}")


async def _replication(urls: list[str]) -> Any:
    """The shared agent registry's stream as NATS reports it: its RAFT leader and replicas."""
    nc = await nats.connect(servers=urls, connect_timeout=5, max_reconnect_attempts=2)
    try:
        info = await asyncio.wait_for(nc.jetstream().stream_info("KV_fleet_agents"), 10)
        return info.config.num_replicas, info.cluster
    finally:
        await nc.close()


async def test_gcs_cluster_up_starts_nats_and_daemons_and_ctrl_c_stops_every_child(tmp_path: Path) -> None:
    reason = missing_reason()
    if reason is not None:
        pytest.skip(reason)
    ready, log = tmp_path / "ready.json", tmp_path / "up.log"
    with log.open("wb") as out:
        process = subprocess.Popen(
            [str(BIN / "gcs"), "cluster", "up", "--daemons", "2", "--ready-file", str(ready)],
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    info: dict[str, Any] = {}
    try:
        info = await _ready(process, ready, log)
        daemons = info["daemons"]
        assert [d["name"] for d in daemons] == ["gcs-1", "gcs-2"]
        assert len(info["nats"]) == 3 and len(info["pids"]) == 5 and info["replicas"] == 3
        printed = log.read_text()
        for daemon in daemons:
            assert daemon["api"] in printed and f"127.0.0.1:{daemon['agent_port']}" in printed

        # Both APIs answer, each a member of the cluster on the three NATS servers, one token.
        airspace = set()
        for daemon in daemons:
            async with httpx.AsyncClient(base_url=daemon["api"], timeout=10) as api:
                cluster = (await api.get("/api/v1/cluster")).json()
                assert cluster["daemon_id"] == daemon["name"] and cluster["connected"], cluster
                assert sorted(cluster["servers"]) == sorted(info["nats"]), cluster
                airspace.add(cluster["airspace"])
                auth = {"Authorization": f"Bearer {info['token']}"}
                assert (await api.post("/api/v1/fleet/hold", headers=auth)).status_code == 200
        assert len(airspace) == 1 and airspace <= {"gcs-1", "gcs-2"}, airspace  # one shared fleet

        # The NATS cluster formed: the shared buckets have a RAFT leader and two peers.
        replicas, raft = await _replication(info["nats"])
        assert replicas == 3 and raft is not None and raft.leader, raft
        assert len(raft.replicas or []) == 2, raft

        process.send_signal(signal.SIGINT)  # what a terminal's Ctrl-C sends
        deadline = time.monotonic() + 30
        while process.poll() is None and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        assert process.returncode == 0, log.read_text()[-2000:]
        assert [pid for pid in info["pids"] if _alive(pid)] == []
        assert "stopped: every daemon and nats-server" in log.read_text()
        assert not Path(info["base_dir"]).exists()  # the temporary directory went with them
    finally:
        if process.poll() is None:
            process.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(5)
        for pid in info.get("pids", []):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if info.get("base_dir"):
            shutil.rmtree(info["base_dir"], ignore_errors=True)
