"""`gcs serve --cluster` as a real process (kill -9 tests and bench/bench_cluster.py)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from tests.support.processes import BIN


@dataclass
class ServeProcess:
    name: str
    data_dir: Path
    process: subprocess.Popen[bytes]
    agent_port: int = 0
    http_port: int = 0

    @property
    def token(self) -> str:
        return (self.data_dir / "api.token").read_text().strip()

    @property
    def api(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    def kill(self) -> None:
        """SIGKILL: the base station loses power mid-mission."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(5)

    def pause(self) -> None:
        """SIGSTOP: a GC pause, a frozen VM, an overloaded host (resume with :meth:`resume`)."""
        self.process.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.resume()  # a paused daemon would never see the SIGTERM
            self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()


def start_serve(
    name: str,
    base: Path,
    nats_urls: str,
    key_hex: str,
    lease_ttl_s: float = 2.0,
    timeout: float = 20.0,
    env: dict[str, str] | None = None,
) -> ServeProcess:
    """Start one clustered daemon on free loopback ports and wait until it listens."""
    data_dir = base / name
    data_dir.mkdir(parents=True, exist_ok=True)
    (data_dir / "fleet.key").write_text(key_hex + "\n")
    ready = data_dir / "ready"
    ready.unlink(missing_ok=True)
    env = {**os.environ, "FLEETGCS_CLUSTER_LEASE_TTL_S": str(lease_ttl_s), **(env or {})}
    log = open(data_dir / "serve.log", "ab")  # noqa: SIM115 - owned by the process
    process = subprocess.Popen(
        [
            str(BIN / "gcs"),
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--http",
            "127.0.0.1:0",
            "--data-dir",
            str(data_dir),
            "--status-period",
            "0.1",
            "--lost-after",
            "20",
            "--cluster",
            nats_urls,
            "--daemon-id",
            name,
            "--ready-file",
            str(ready),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
    )
    log.close()
    served = ServeProcess(name, data_dir, process)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if ready.exists() and ready.read_text().strip():
            served.agent_port, served.http_port = (int(p) for p in ready.read_text().split())
            return served
        if process.poll() is not None:
            raise RuntimeError(f"gcs serve {name} exited with {process.returncode}; see {data_dir}/serve.log")
        time.sleep(0.05)
    served.kill()
    raise RuntimeError(f"gcs serve {name} not ready in {timeout:.0f} s")
