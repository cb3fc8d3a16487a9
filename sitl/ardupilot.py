"""Launch N real ArduCopter SITL binaries instead of the embedded simulator.

Each instance i runs as ``arducopter -I i --model quad --home LAT,LON,ALT,0 --sysid i+1 --defaults
F[,overrides]`` in its own scratch directory (so their eeprom files do not collide; the directory is
removed at :meth:`ArduPilotFleet.stop` unless ``keep_logs``). Vehicle i is served on
``host:base_port + 10*i``, like the embedded simulator.

ArduPilot's TCP serial ports listen on every interface and cannot be bound to one address, so for
any ``host`` but ``0.0.0.0`` SERIAL0 is turned around: the instance connects as a TCP *client*
(``--serial0 tcpclient:127.0.0.1:P``) to a private loopback port of this process, and a relay
thread serves it on ``host:port``, one client at a time, like SITL itself. SERIAL2 is disabled;
SERIAL1 too, unless ``pilot_links``: then it is relayed the same way on ``host:base_port + 10*i + 2``
(an ephemeral port with base_port 0), for a second ground station, a pilot's (issue 26). (The
instance's UDP RC-input port, 5501+10*i, still listens on every interface.)

Dataflash logs (about 28 MB per vehicle per 10 minutes) are written only with ``keep_logs``.
The instances are our children: they get SIGTERM when :meth:`ArduPilotFleet.stop` runs, and on
Linux also PR_SET_PDEATHSIG so they die with us even if we are killed hard.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from sitl.physics import local_to_latlon

ENV_VAR = "ARDUPILOT_SITL"
DEFAULTS_ENV_VAR = "ARDUPILOT_DEFAULTS"
BASE_PORT = 5760
ALL_INTERFACES = "0.0.0.0"
RELAY_CHUNK = 65536
# Without --keep-logs: no dataflash logs (they would be deleted with the scratch directory anyway).
NO_LOG_PARAMS = {"LOG_BACKEND_TYPE": 0.0, "LOG_DISARMED": 0.0}


def find_binary(explicit: str | None = None) -> str | None:
    """The arducopter binary: explicit path, else $ARDUPILOT_SITL, else ``arducopter`` on PATH."""
    for cand in (explicit, os.environ.get(ENV_VAR)):
        if cand:
            p = Path(cand).expanduser()
            if p.is_file() and os.access(p, os.X_OK):
                return str(p.resolve())  # the instances run in their own directories
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


def wind_params(north: float, east: float) -> dict[str, float]:
    """SIM_WIND_SPD/DIR for a wind blowing *toward* north/east (ArduPilot's DIR is where it comes from)."""
    speed = math.hypot(north, east)
    if speed == 0:
        return {"SIM_WIND_SPD": 0.0}
    return {"SIM_WIND_SPD": speed, "SIM_WIND_DIR": (math.degrees(math.atan2(east, north)) + 180.0) % 360.0}


def _die_with_parent() -> None:
    """preexec_fn: ask the kernel to SIGTERM the child when this (parent) process dies."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class _Relay:
    """One thread relaying bytes between each SITL instance (TCP client) and one outside client."""

    def __init__(self) -> None:
        self._sel = selectors.DefaultSelector()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pairs: list[dict[str, socket.socket | None]] = []
        self._lock = threading.Lock()

    def add(self, host: str, port: int) -> tuple[int, int]:
        """Listen on host:port (outside) and on an ephemeral loopback port (SITL); returns both ports."""
        outside = socket.create_server((host, port), reuse_port=False)
        inside = socket.create_server(("127.0.0.1", 0))
        for s in (outside, inside):
            s.setblocking(False)
        index = len(self._pairs)
        self._pairs.append({"outside": outside, "inside": inside, "sitl": None, "client": None})
        self._sel.register(outside, selectors.EVENT_READ, (index, "accept-client"))
        self._sel.register(inside, selectors.EVENT_READ, (index, "accept-sitl"))
        return outside.getsockname()[1], inside.getsockname()[1]

    @property
    def pairs(self) -> int:
        """How many ports are relayed (the index the next :meth:`add` gets)."""
        return len(self._pairs)

    def sitl_connected(self, index: int) -> bool:
        with self._lock:
            return self._pairs[index]["sitl"] is not None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="ardupilot-relay", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for pair in self._pairs:
            for sock in pair.values():
                if sock is not None:
                    with contextlib.suppress(OSError):
                        sock.close()
        self._sel.close()

    def _drop(self, index: int, which: str) -> None:
        sock = self._pairs[index][which]
        if sock is None:
            return
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(sock)
        with contextlib.suppress(OSError):
            sock.close()
        with self._lock:
            self._pairs[index][which] = None

    def _run(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(timeout=0.2):
                index, role = key.data
                pair = self._pairs[index]
                if role.startswith("accept-"):
                    which = "client" if role == "accept-client" else "sitl"
                    listener = key.fileobj
                    assert isinstance(listener, socket.socket)
                    try:
                        conn, _ = listener.accept()
                    except OSError:
                        continue
                    if pair[which] is not None:  # one client at a time, like SITL's own ports
                        conn.close()
                        continue
                    conn.setblocking(True)
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    with self._lock:
                        pair[which] = conn
                    self._sel.register(conn, selectors.EVENT_READ, (index, which))
                    continue
                sock = pair[role]
                if sock is None:
                    continue
                try:
                    data = sock.recv(RELAY_CHUNK)
                except OSError:
                    data = b""
                if not data:
                    self._drop(index, role)
                    continue
                peer = pair["client" if role == "sitl" else "sitl"]
                if peer is None:
                    continue  # nobody on the other side: bytes are lost, as on a serial line
                try:
                    peer.sendall(data)
                except OSError:
                    self._drop(index, "client" if role == "sitl" else "sitl")


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
        *,
        base_port: int = BASE_PORT,
        host: str = "127.0.0.1",
        params: dict[str, float] | None = None,
        keep_logs: bool = False,
        pilot_links: bool = False,
    ) -> None:
        if not 1 <= vehicles <= 250:
            raise ValueError("vehicles must be 1..250 (system ids 1..250)")
        if base_port and not 1024 <= base_port <= 65535 - 10 * (vehicles - 1) - 3:
            raise ValueError(f"base port {base_port} out of range for {vehicles} vehicles")
        if base_port == 0 and host == ALL_INTERFACES:
            raise ValueError("base port 0 (ephemeral ports) needs a host other than 0.0.0.0")
        self.binary = str(Path(binary).resolve()) if os.sep in binary else binary
        self.n = vehicles
        self.home = home
        self.spacing_m = spacing_m
        self.speedup = speedup
        self.defaults = defaults if defaults is not None else find_defaults(binary)
        self.extra_args = extra_args or []
        self.base_port = base_port
        self.host = host
        self.keep_logs = keep_logs
        self.params = {
            **({} if keep_logs else NO_LOG_PARAMS),
            **{k.upper(): v for k, v in (params or {}).items()},
        }
        self.procs: list[subprocess.Popen[bytes]] = []
        self.workdir = tempfile.mkdtemp(prefix="fleetgcs-ardupilot-")
        self._relay: _Relay | None = None
        self._sitl_ports: list[int] = []
        self._relay_index: list[int] = []  # the relay pair of each instance's SERIAL0
        self.pilot_links = pilot_links
        self._pilot_ports: list[int] = [base_port + 10 * i + 2 if base_port else 0 for i in range(vehicles)]
        self._sitl_pilot_ports: list[int] = []
        # base_port 0: every instance gets its own ephemeral port (not 0, 10, 20...).
        self._ports: list[int] = [base_port + 10 * i if base_port else 0 for i in range(vehicles)]

    @property
    def relayed(self) -> bool:
        """True when SERIAL0 goes through our relay (every host but 0.0.0.0)."""
        return self.host != ALL_INTERFACES

    @property
    def endpoints(self) -> list[str]:
        """SERIAL0 TCP endpoints, base_port + 10*i."""
        host = "127.0.0.1" if self.host == ALL_INTERFACES else self.host
        return [f"tcp:{host}:{port}" for port in self._ports]

    @property
    def pilot_endpoints(self) -> list[str]:
        """SERIAL1 TCP endpoints for a second ground station (``pilot_links``), one per vehicle."""
        if not self.pilot_links:
            return []
        host = "127.0.0.1" if self.host == ALL_INTERFACES else self.host
        return [f"tcp:{host}:{port}" for port in self._pilot_ports]

    def _defaults_arg(self) -> str | None:
        files = [self.defaults] if self.defaults else []
        if self.params:
            extra = Path(self.workdir) / "overrides.parm"
            extra.write_text("".join(f"{name} {value:g}\n" for name, value in self.params.items()))
            files.append(str(extra))
        return ",".join(files) or None

    def command(self, i: int) -> list[str]:
        """Command line of instance ``i``."""
        lat, lon = local_to_latlon(self.home[0], self.home[1], 0.0, i * self.spacing_m)
        alt = self.home[2] if len(self.home) > 2 else 0.0
        cmd = [
            self.binary,
            "--wipe",  # fresh parameters: only the defaults files count
            *(["--base-port", str(self.base_port)] if self.base_port else []),
            "-I",
            str(i),
            "--model",
            "quad",
            "--home",
            f"{lat:.7f},{lon:.7f},{alt:.2f},0",
            "--sysid",
            str(i + 1),
        ]
        if self.relayed and i < len(self._sitl_ports):
            serial1 = f"tcpclient:127.0.0.1:{self._sitl_pilot_ports[i]}" if self.pilot_links else "none"
            cmd += [
                "--serial0",
                f"tcpclient:127.0.0.1:{self._sitl_ports[i]}",
                "--serial1",
                serial1,
                "--serial2",
                "none",
            ]
        if self.speedup != 1.0:
            cmd += ["--speedup", f"{self.speedup:g}"]
        defaults = self._defaults_arg()
        if defaults:
            cmd += ["--defaults", defaults]
        return cmd + self.extra_args

    def start(self, timeout: float = 60.0) -> ArduPilotFleet:
        """Start every instance and wait until each SERIAL0 is ready for a client.

        Relayed: the instance has connected to our private port. Direct (0.0.0.0): its port accepts
        a TCP connection (closed at once; SITL then waits for the next client).
        """
        try:
            if self.relayed:
                self._relay = _Relay()
                for i in range(self.n):
                    self._relay_index.append(self._relay.pairs)
                    outside, inside = self._relay.add(self.host, self._ports[i])
                    self._ports[i] = outside
                    self._sitl_ports.append(inside)
                    if self.pilot_links:
                        outside, inside = self._relay.add(self.host, self._pilot_ports[i])
                        self._pilot_ports[i] = outside
                        self._sitl_pilot_ports.append(inside)
                self._relay.start()
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
                log.close()
            deadline = time.monotonic() + timeout
            for i in range(self.n):
                self._wait_ready(i, deadline)
        except BaseException:
            self.stop()
            raise
        return self

    def _wait_ready(self, i: int, deadline: float) -> None:
        while True:
            if self.procs[i].poll() is not None:
                tail = self._log_tail(i)
                raise RuntimeError(f"arducopter instance {i} exited early: {tail}")
            if self._relay is not None:
                if self._relay.sitl_connected(self._relay_index[i]):
                    return
            else:
                with (
                    contextlib.suppress(OSError),
                    socket.create_connection(("127.0.0.1", self._ports[i]), 0.5),
                ):
                    return
            if time.monotonic() > deadline:
                raise RuntimeError(f"arducopter instance {i} did not open SERIAL0 ({self.endpoints[i]})")
            time.sleep(0.1)

    def _log_tail(self, i: int) -> str:
        try:
            lines = (Path(self.workdir) / f"I{i}" / "arducopter.log").read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return " | ".join(lines[-3:]) or "(empty log)"

    def alive(self) -> bool:
        """True while every instance runs."""
        return bool(self.procs) and all(p.poll() is None for p in self.procs)

    def stop(self) -> None:
        """SIGTERM every instance (SIGKILL after 5 s), stop the relay, remove the scratch directory."""
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
        if self._relay is not None:
            self._relay.stop()
            self._relay = None
        if not self.keep_logs:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def __enter__(self) -> ArduPilotFleet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
