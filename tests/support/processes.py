"""The console scripts as processes: where they are, `gcs serve` started on loopback, and its ready file.

One place for what the CLI, fault, API and cluster tests each used to write again (issue 24)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent
"""The venv's bin folder: `gcs`, `agent` and `sitl` of the interpreter running the tests."""


def serve_daemon(
    data_dir: Path,
    ready: Path,
    listen: str = "127.0.0.1:0",
    env: dict[str, str] | None = None,
    *,
    options: tuple[str, ...] = ("--status-period", "0.1", "--lost-after", "20"),
    stderr: int = subprocess.DEVNULL,
) -> subprocess.Popen[bytes]:
    """``gcs serve`` as its own process (so a test can SIGKILL it) on loopback with HTTP on a free port;
    ``options`` follow (status every 0.1 s, lost after 20 s unless told), ``env`` adds environment
    variables (``FLEETGCS_...`` settings); ``stderr=subprocess.PIPE`` lets :func:`wait_ready` show why
    a daemon that exits early did."""
    ready.unlink(missing_ok=True)
    command: list[str | Path] = [BIN / "gcs", "serve", "--listen", listen, "--http", "127.0.0.1:0"]
    command += ["--data-dir", data_dir, *options, "--ready-file", ready]
    return subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=stderr, env={**os.environ, **(env or {})}
    )


def agent_process(
    name: str, port: int, key_file: Path, position: tuple[float, float, float], speedup: float
) -> subprocess.Popen[bytes]:
    """``agent run`` on a memory autopilot at ``position`` (lat, lon, alt AMSL), joining a daemon on
    loopback ``port`` with the fleet key in ``key_file``; its output is not read."""
    lat, lon, alt = position
    return subprocess.Popen(
        [
            BIN / "agent",
            "run",
            "--gcs",
            f"127.0.0.1:{port}",
            "--id",
            name,
            "--key-file",
            key_file,
            "--autopilot-backend",
            "memory",
            "--autopilot",
            f"{lat},{lon},{alt}",
            "--speedup",
            f"{speedup:g}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def stop_processes(procs: list[subprocess.Popen[bytes]], timeout: float = 10.0) -> None:
    """SIGTERM every process still running, then reap each; one that outlasts ``timeout`` is killed."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=timeout)


def wait_ready(path: Path, proc: subprocess.Popen[bytes], timeout: float = 20.0) -> tuple[int, int]:
    """The (agent port, HTTP port) a ``gcs serve --ready-file`` wrote, once it is ready (bounded); a
    daemon that exits first fails the test with its exit code and, when piped, its stderr."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().strip():
            agent_port, http_port = (int(p) for p in path.read_text().split())
            return agent_port, http_port
        if proc.poll() is not None:
            detail = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
            raise AssertionError(f"gcs serve exited with {proc.returncode}: {detail}")
        time.sleep(0.05)
    raise AssertionError("gcs serve did not become ready")


@dataclass(frozen=True)
class ServeResult:
    started: bool  # it wrote its ready file (then it was stopped with SIGTERM)
    returncode: int
    stderr: str


def run_serve(data_dir: Path, *extra: str, start_timeout_s: float = 60.0) -> ServeResult:
    """Run ``gcs serve --data-dir DATA_DIR`` on free loopback ports without HTTP until it is ready
    (then SIGTERM) or exits by itself; bounded by ``start_timeout_s``, the process always reaped."""
    ready = data_dir.parent / f"{data_dir.name}.ready"
    ready.unlink(missing_ok=True)
    command = [str(BIN / "gcs"), "serve", "--data-dir", str(data_dir), "--listen", "127.0.0.1:0"]
    command += ["--http", "none", "--ready-file", str(ready), *extra]
    with subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as daemon:
        try:
            deadline = time.monotonic() + start_timeout_s
            while time.monotonic() < deadline and daemon.poll() is None and not ready.exists():
                time.sleep(0.05)
        finally:
            if daemon.poll() is None:
                daemon.send_signal(signal.SIGTERM)
            try:
                _, stderr = daemon.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                daemon.kill()
                _, stderr = daemon.communicate()
    return ServeResult(ready.exists(), daemon.returncode, stderr)
