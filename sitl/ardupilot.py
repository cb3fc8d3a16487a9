"""Launch N real ArduCopter SITL binaries instead of the embedded simulator.

Each instance i runs as ``arducopter -I i --model quad --home LAT,LON,ALT,0 --sysid i+1 [--defaults F]`` in
its own working directory (so their eeprom files do not collide), listening on SERIAL0 = 5760 + 10*i.
The instances are our children: they get SIGTERM when :meth:`ArduPilotFleet.stop` runs, and on Linux
also PR_SET_PDEATHSIG so they die with us even if we are killed hard.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sitl.physics import local_to_latlon

ENV_VAR = "ARDUPILOT_SITL"
DEFAULTS_ENV_VAR = "ARDUPILOT_DEFAULTS"
BASE_PORT = 5760


def find_binary(explicit: str | None = None) -> str | None:
    """The arducopter binary: explicit path, else $ARDUPILOT_SITL, else ``arducopter`` on PATH."""
    for cand in (explicit, os.environ.get(ENV_VAR)):
        if cand:
            p = Path(cand).expanduser()
            if p.is_file() and os.access(p, os.X_OK):
                return str(p)
            found = shutil.which(cand)
            if found:
                return found
    return shutil.which("arducopter")


def find_defaults(binary: str) -> str | None:
    """A copter defaults file: $ARDUPILOT_DEFAULTS, or Tools/autotest/default_params/copter.parm found
    walking up from the binary (the layout of an ArduPilot checkout's build/sitl/bin)."""
    env = os.environ.get(DEFAULTS_ENV_VAR)
    if env and Path(env).is_file():
        return env
    here = Path(binary).resolve().parent
    for parent in [here, *here.parents][:6]:
        for rel in ("Tools/autotest/default_params/copter.parm", "copter.parm", "default_params/copter.parm"):
            cand = parent / rel
            if cand.is_file():
                return str(cand)
    return None


def _die_with_parent() -> None:
    """preexec_fn: ask the kernel to SIGTERM the child when this (parent) process dies."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class ArduPilotFleet:
    """N ``arducopter`` processes with the same endpoints contract as :class:`sitl.fleet.SimFleet`."""

    def __init__(
        self,
        binary: str,
        vehicles: int,
        home: tuple[float, ...],
        spacing_m: float = 5.0,
        speedup: float = 1.0,
        defaults: str | None = None,
        extra_args: list[str] | None = None,
    ) -> None:
        self.binary = binary
        self.n = vehicles
        self.home = home
        self.spacing_m = spacing_m
        self.speedup = speedup
        self.defaults = defaults if defaults is not None else find_defaults(binary)
        self.extra_args = extra_args or []
        self.procs: list[subprocess.Popen[bytes]] = []
        self.workdir = tempfile.mkdtemp(prefix="fleetgcs-ardupilot-")

    @property
    def endpoints(self) -> list[str]:
        """SERIAL0 TCP endpoints, 5760 + 10*i."""
        return [f"tcp:127.0.0.1:{BASE_PORT + 10 * i}" for i in range(self.n)]

    def command(self, i: int) -> list[str]:
        """Command line of instance ``i``."""
        lat, lon = local_to_latlon(self.home[0], self.home[1], 0.0, i * self.spacing_m)
        alt = self.home[2] if len(self.home) > 2 else 0.0
        cmd = [
            self.binary,
            "-I",
            str(i),
            "--model",
            "quad",
            "--home",
            f"{lat:.7f},{lon:.7f},{alt:.2f},0",
            "--sysid",
            str(i + 1),
        ]
        if self.speedup != 1.0:
            cmd += ["--speedup", f"{self.speedup:g}"]
        if self.defaults:
            cmd += ["--defaults", self.defaults]
        return cmd + self.extra_args

    def start(self, timeout: float = 60.0) -> ArduPilotFleet:
        """Start every instance and wait until each SERIAL0 port accepts TCP connections.

        Readiness is probed with a connect that is closed at once; SITL then waits for the next client.
        """
        for i in range(self.n):
            wd = Path(self.workdir) / f"I{i}"
            wd.mkdir(parents=True, exist_ok=True)
            log = open(wd / "arducopter.log", "wb")  # noqa: SIM115 - owned by the child for its lifetime
            self.procs.append(
                subprocess.Popen(
                    self.command(i),
                    cwd=wd,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL,
                    preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
                )
            )
        deadline = time.monotonic() + timeout
        for i in range(self.n):
            port = BASE_PORT + 10 * i
            while True:
                if self.procs[i].poll() is not None:
                    self.stop()
                    raise RuntimeError(f"arducopter instance {i} exited early (log in {self.workdir}/I{i})")
                try:
                    with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                        break
                except OSError:
                    if time.monotonic() > deadline:
                        self.stop()
                        raise RuntimeError(f"arducopter instance {i} did not open port {port}") from None
                    time.sleep(0.2)
        return self

    def alive(self) -> bool:
        """True while every instance runs."""
        return bool(self.procs) and all(p.poll() is None for p in self.procs)

    def stop(self) -> None:
        """SIGTERM every instance, SIGKILL after 5 s."""
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        deadline = time.monotonic() + 5.0
        for p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(2.0)
        self.procs.clear()
