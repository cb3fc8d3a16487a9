"""Start and stop ``nats-server -js`` on loopback (tests, bench, a quick local cluster).

Debian's ``nats-server`` package (``scripts/bootstrap`` installs it when it can). Each server gets
free loopback ports and its own store directory; :class:`NatsCluster` runs three clustered servers
(JetStream meta-group and streams replicated by RAFT). Every wait is bounded; ``stop`` always
kills what ``start`` began.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

READY_TIMEOUT_S = 15.0


def nats_server_binary() -> str | None:
    """Path of ``nats-server`` (PATH, then Debian's /usr/sbin), or None."""
    found = shutil.which("nats-server")
    if found:
        return found
    return "/usr/sbin/nats-server" if os.access("/usr/sbin/nats-server", os.X_OK) else None


def missing_reason() -> str | None:
    """Why NATS tests cannot run here (None when they can)."""
    if nats_server_binary() is None:
        return "nats-server not installed (scripts/bootstrap installs Debian's package as root)"
    try:
        import nats  # noqa: F401
    except ImportError:
        return "nats-py not installed (pip install -e '.[gcs]')"
    return None


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _wait_port(port: int, process: subprocess.Popen[bytes], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"nats-server exited with {process.returncode}")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return
        time.sleep(0.05)
    raise RuntimeError(f"nats-server did not listen on {port} within {timeout:.0f} s")


@dataclass
class NatsServer:
    """One ``nats-server -js`` on 127.0.0.1; ``cluster_port``/``routes`` make it a cluster member."""

    store_dir: Path
    name: str = "n1"
    port: int = field(default_factory=free_port)
    cluster_port: int | None = None
    routes: list[int] = field(default_factory=list)
    process: subprocess.Popen[bytes] | None = None
    own_session: bool = False  # a session of its own: a terminal's Ctrl-C reaches only its starter

    @property
    def url(self) -> str:
        return f"nats://127.0.0.1:{self.port}"

    def start(self) -> None:
        binary = nats_server_binary()
        if binary is None:
            raise RuntimeError(missing_reason() or "nats-server missing")
        self.store_dir.mkdir(parents=True, exist_ok=True)
        command = [binary, "-js", "-a", "127.0.0.1", "-p", str(self.port), "-sd", str(self.store_dir)]
        command += ["-n", self.name]
        if self.cluster_port is not None:
            command += ["--cluster_name", "fleet", "--cluster", f"nats://127.0.0.1:{self.cluster_port}"]
            command += ["--routes", ",".join(f"nats://127.0.0.1:{p}" for p in self.routes)]
        log = open(self.store_dir / "server.log", "ab")  # noqa: SIM115 - owned by the process
        self.process = subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, start_new_session=self.own_session
        )
        log.close()
        _wait_port(self.port, self.process, READY_TIMEOUT_S)

    def kill(self) -> None:
        """SIGKILL (a base station losing power); bounded wait for the process to go."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(5)

    def stop(self) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.terminate()
        try:
            self.process.wait(5)
        except subprocess.TimeoutExpired:
            self.kill()


@dataclass
class NatsCluster:
    """Three clustered servers (the smallest RAFT group that survives one loss)."""

    base_dir: Path
    size: int = 3
    servers: list[NatsServer] = field(default_factory=list)
    own_session: bool = False  # each server in a session of its own (:attr:`NatsServer.own_session`)

    def start(self) -> None:
        cluster_ports = [free_port() for _ in range(self.size)]
        for index in range(self.size):
            others = [p for i, p in enumerate(cluster_ports) if i != index]
            server = NatsServer(
                self.base_dir / f"n{index + 1}",
                name=f"n{index + 1}",
                cluster_port=cluster_ports[index],
                routes=others,
                own_session=self.own_session,
            )
            self.servers.append(server)
        try:
            for server in self.servers:
                server.start()
        except Exception:
            self.stop()
            raise

    @property
    def urls(self) -> str:
        return ",".join(s.url for s in self.servers)

    def stop(self) -> None:
        for server in self.servers:
            server.stop()
