"""``gcs cluster up``: a whole cluster on this machine, for trying cluster mode (docs/cluster.md).

A three-node NATS JetStream cluster (``nats-server`` processes on loopback, gcs/cluster/natsrun.py)
and N ``gcs serve --cluster`` daemons sharing one fleet key and one API token, each with its data
directory under one base directory. Every child runs in a session of its own, so a terminal's
Ctrl-C reaches only the starter, which stops them in order: the daemons first (they hand their
leases back while NATS still answers), then NATS. Every wait is bounded; :meth:`LocalCluster.stop`
stops whatever :meth:`LocalCluster.start` began, also after a failed start.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from gcs.cluster.natsrun import NatsCluster, NatsServer, missing_reason

READY_TIMEOUT_S = 60.0  # a daemon waits up to 5 s for NATS and 20 s for JetStream, plus its start
STOP_TIMEOUT_S = 10.0
LEASE_TTL_REPLICATED_S = 8.0  # rides through a NATS stream's leader election (docs/cluster.md)


class LocalClusterError(Exception):
    """The local cluster could not start (one line, with the log to read)."""


@dataclass
class LocalDaemon:
    """One ``gcs serve --cluster`` child."""

    name: str
    data_dir: Path
    process: subprocess.Popen[bytes]
    agent_port: int = 0
    http_port: int = 0

    @property
    def api(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def log(self) -> Path:
        return self.data_dir / "serve.log"


def _port(base: int, index: int) -> int:
    return base + index if base else 0


@dataclass
class LocalCluster:
    """``nats_nodes`` NATS servers (clustered when more than one) and ``daemons`` daemons. The fleet
    key and the API token are made once per base directory (``fleet.key``, ``api.token``) and
    copied into every daemon's data directory."""

    base_dir: Path
    daemons: int = 2
    nats_nodes: int = 3
    agent_port: int = 0  # first daemon's agent port (the next ones count up); 0: free ports
    http_port: int = 0  # first daemon's API port (likewise)
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24))
    nats: list[NatsServer] = field(default_factory=list)
    serves: list[LocalDaemon] = field(default_factory=list)

    @property
    def replicas(self) -> int:
        return min(3, self.nats_nodes)

    @property
    def nats_urls(self) -> str:
        return ",".join(server.url for server in self.nats)

    @property
    def key_file(self) -> Path:
        return self.base_dir / "fleet.key"

    def pids(self) -> list[int]:
        """Every child process started (NATS servers and daemons)."""
        processes = [s.process for s in self.nats] + [d.process for d in self.serves]
        return [p.pid for p in processes if p is not None]

    # --- start and stop ------------------------------------------------------------------------

    def start(self) -> None:
        """NATS, then every daemon at once; returns when all listen (LocalClusterError if not)."""
        reason = missing_reason()
        if reason is not None:
            raise LocalClusterError(reason)
        self.base_dir.mkdir(parents=True, exist_ok=True)
        token_file = self.base_dir / "api.token"
        for path, new in ((self.key_file, secrets.token_hex(32)), (token_file, self.token)):
            if not path.exists():  # a kept --dir keeps its key and token: configured agents still join
                path.touch(mode=0o600)
                path.write_text(new + "\n")
        self.token = token_file.read_text().strip()
        self._start_nats()
        for index in range(self.daemons):
            self.serves.append(self._spawn(index))
        deadline = time.monotonic() + READY_TIMEOUT_S
        for serve in self.serves:
            self._wait_ready(serve, deadline)
        (self.base_dir / "agent.toml").write_text(self.agent_toml())

    def _start_nats(self) -> None:
        nats_dir = self.base_dir / "nats"
        if self.nats_nodes == 1:
            server = NatsServer(nats_dir / "n1", own_session=True)
            self.nats.append(server)
            server.start()
            return
        cluster = NatsCluster(nats_dir, size=self.nats_nodes, own_session=True)
        try:
            cluster.start()
        finally:
            self.nats = cluster.servers  # stopped by stop() whatever happened

    def _spawn(self, index: int) -> LocalDaemon:
        name = f"gcs-{index + 1}"
        data_dir = self.base_dir / name
        data_dir.mkdir(parents=True, exist_ok=True)
        (data_dir / "fleet.key").write_text(self.key_file.read_text())  # one fleet key for all
        token = data_dir / "api.token"
        token.touch(mode=0o600)
        token.write_text(self.token + "\n")  # one API token: any daemon's API takes it
        (data_dir / "ready").unlink(missing_ok=True)
        env = {**os.environ, "FLEETGCS_CLUSTER_REPLICAS": str(self.replicas)}
        if self.replicas > 1:
            env["FLEETGCS_CLUSTER_LEASE_TTL_S"] = str(LEASE_TTL_REPLICATED_S)
        command = [sys.executable, "-m", "gcs", "serve", "--daemon-id", name, "--cluster", self.nats_urls]
        command += ["--listen", f"127.0.0.1:{_port(self.agent_port, index)}"]
        command += ["--http", f"127.0.0.1:{_port(self.http_port, index)}"]
        command += ["--data-dir", str(data_dir), "--ready-file", str(data_dir / "ready")]
        with open(data_dir / "serve.log", "ab") as log:
            process = subprocess.Popen(
                command, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True
            )
        return LocalDaemon(name, data_dir, process)

    @staticmethod
    def _wait_ready(serve: LocalDaemon, deadline: float) -> None:
        ready = serve.data_dir / "ready"
        while time.monotonic() < deadline:
            text = ready.read_text().strip() if ready.exists() else ""
            if text:
                serve.agent_port, serve.http_port = (int(p) for p in text.split())
                return
            if serve.process.poll() is not None:
                raise LocalClusterError(
                    f"{serve.name} exited with {serve.process.returncode}; see {serve.log}"
                )
            time.sleep(0.05)
        raise LocalClusterError(f"{serve.name} not ready within {READY_TIMEOUT_S:.0f} s; see {serve.log}")

    def exited(self) -> list[str]:
        """Children that ended by themselves (or were killed to try a failure), one line each."""
        gone = [
            f"{d.name} exited with {d.process.returncode}; see {d.log}"
            for d in self.serves
            if d.process.poll() is not None
        ]
        for server in self.nats:
            if server.process is not None and server.process.poll() is not None:
                gone.append(f"nats-server {server.name} exited; see {server.store_dir / 'server.log'}")
        return gone

    def stop(self) -> None:
        """Daemons first (SIGTERM: a clean stop hands their leases over), then NATS; bounded."""
        for serve in self.serves:
            if serve.process.poll() is None:
                serve.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for serve in self.serves:
            try:
                serve.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                serve.process.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    serve.process.wait(5)
        for server in self.nats:
            server.stop()

    # --- what the operator reads -----------------------------------------------------------------

    def agent_toml(self) -> str:
        """An agent configuration listing every daemon (the first one first)."""
        first, *others = self.serves
        return (
            "# written by gcs cluster up: an agent of this local cluster (docs/cluster.md)\n"
            "[agent]\n"
            'gcs_host = "127.0.0.1"\n'
            f"gcs_port = {first.agent_port}\n"
            f"daemons = {json.dumps([f'127.0.0.1:{d.agent_port}' for d in others])}\n"
        )

    def describe(self) -> dict[str, object]:
        """What ``--ready-file`` holds (JSON): where everything listens, every child's pid."""
        return {
            "base_dir": str(self.base_dir),
            "nats": [server.url for server in self.nats],
            "replicas": self.replicas,
            "key_file": str(self.key_file),
            "token": self.token,
            "daemons": [
                {
                    "name": d.name,
                    "api": d.api,
                    "agent_port": d.agent_port,
                    "data_dir": str(d.data_dir),
                    "pid": d.process.pid,
                }
                for d in self.serves
            ],
            "pids": self.pids(),
        }

    def banner(self) -> str:
        """How to reach it, as the operator reads it once it is up."""
        kind = f"{self.nats_nodes}-node JetStream cluster" if self.nats_nodes > 1 else "one JetStream server"
        lines = [
            f"NATS ({kind}, replicas {self.replicas}): {self.nats_urls}",
            *(
                f"{d.name}: API {d.api}  agents 127.0.0.1:{d.agent_port}  data {d.data_dir}"
                for d in self.serves
            ),
            f"fleet key {self.key_file}; API token (every daemon) {self.token}",
            "",
            "try it:",
            f"  gcs agents --api {self.serves[0].api} --token {self.token}",
            f"  curl {self.serves[-1].api}/api/v1/cluster",
            "  sitl run --vehicles 2 --base-port 5760",
            f"  agent run --config {self.base_dir / 'agent.toml'} --id drone-1 --key-file {self.key_file} "
            "--autopilot tcp:127.0.0.1:5760",
            f"  gcs run MISSION.json --api {self.serves[0].api} --token {self.token}",
            f"logs: {self.base_dir}/gcs-*/serve.log, {self.base_dir}/nats/*/server.log",
            "Ctrl-C stops everything.",
        ]
        return "\n".join(lines)
