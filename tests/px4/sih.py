"""Real PX4 SITL (v1.16, SIH physics inside the PX4 process) for the tests: where the binary is, and a
fleet of instances started and stopped by this process.

Instance ``i`` is ``bin/px4 -i i -d etc`` in its own scratch directory (parameters and missions do not
leak between runs), MAV_SYS_ID ``i+1``, and sends its API link to UDP ``14540+i`` (the agent listens
there: ``udpin:127.0.0.1:14540+i``). PX4 sends the API link of every instance from 10 on to the one
port 14549, so a fleet's instances must lie in 0-9. Instance ids are machine-wide
(``/tmp/px4_lock-<i>``): each fleet takes a block of ids under an advisory file lock, so two test
processes asking for the same block run one after the other instead of failing (bounded wait).
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import shutil
import subprocess
import time
from pathlib import Path
from typing import IO

from sitl.ardupilot import _die_with_parent
from tests.support.paths import ROOT

DEFAULT = ROOT.parent / "shared" / "px4"
ENV_VAR = "PX4_SITL_DIR"
API_PORT_BASE = 14540
MAX_INSTANCE = 9  # from 10 on PX4 sends every API link to 14549
EARTH_R = 6378137.0
# No .ulg logs (about 15 MB per flight); quiet boot.
BASE_PARAMS: dict[str, str] = {"SDLOG_MODE": "-1"}


def px4_dir() -> Path | None:
    """The PX4 SITL folder (bin/px4 + etc/): $PX4_SITL_DIR, else ../shared/px4 beside the repository."""
    env = os.environ.get(ENV_VAR)
    for cand in (Path(env).expanduser() if env else None, DEFAULT):
        if cand is not None and (cand / "bin" / "px4").is_file() and os.access(cand / "bin" / "px4", os.X_OK):
            return cand.resolve()
    return None


SKIP_REASON = (
    f"real PX4 SITL not available: set {ENV_VAR} to a folder with bin/px4 and etc/, or put one at {DEFAULT}"
)


def _preexec(nice: int) -> None:
    _die_with_parent()
    with contextlib.suppress(OSError):
        os.nice(nice)


class PX4Fleet:
    """``vehicles`` PX4 SIH quadcopters, instances ``first..first+vehicles-1``, homes ``spacing_m`` east."""

    def __init__(
        self,
        px4: Path,
        workdir: Path,
        first: int,
        vehicles: int,
        home: tuple[float, float, float],
        spacing_m: float,
        params: dict[str, float] | None = None,
        speed_factor: float = 1.0,
        nice: int = 10,
    ) -> None:
        if first < 0 or first + vehicles - 1 > MAX_INSTANCE:
            raise ValueError(f"PX4 instances {first}..{first + vehicles - 1}: must lie in 0..{MAX_INSTANCE}")
        self.px4, self.workdir, self.first, self.vehicles = px4, workdir, first, vehicles
        self.home, self.spacing_m, self.speed_factor, self.nice = home, spacing_m, speed_factor, nice
        self.params = {**BASE_PARAMS, **{k: repr(float(v)) for k, v in (params or {}).items()}}
        self.procs: list[subprocess.Popen[bytes]] = []
        self._lock: IO[str] | None = None

    @property
    def instances(self) -> list[int]:
        return list(range(self.first, self.first + self.vehicles))

    @property
    def endpoints(self) -> list[str]:
        """What an agent connects to (pymavlink form; the MAVSDK backend translates it)."""
        return [f"udpin:127.0.0.1:{API_PORT_BASE + i}" for i in self.instances]

    def home_of(self, index: int) -> tuple[float, float, float]:
        lat, lon, alt = self.home
        dlon = self.spacing_m * index / (EARTH_R * math.cos(math.radians(lat)))
        return lat, lon + math.degrees(dlon), alt

    def _bin(self) -> Path:
        """A bin folder of links to the PX4 binary: its module commands (``px4-param``, ...) must be
        links to ``px4`` on the PATH, and a copied or unpacked tree may hold them as plain files."""
        bindir = self.workdir / "bin"
        shutil.rmtree(bindir, ignore_errors=True)
        bindir.mkdir(parents=True)
        real = self.px4 / "bin" / "px4"
        for entry in (self.px4 / "bin").iterdir():
            module = entry.name.startswith("px4-") and not entry.name.endswith(".sh")
            (bindir / entry.name).symlink_to(real if module or entry.name == "px4" else entry)
        return bindir

    def _command(self, bindir: Path) -> list[str]:
        # As root PX4 makes SCHED_FIFO threads that ignore nice and starve a small machine.
        root = os.geteuid() == 0 and shutil.which("setpriv")
        wrap = ["setpriv", "--bounding-set", "-sys_nice"] if root else []
        return [*wrap, str(bindir / "px4")]

    def _acquire(self, timeout: float) -> None:
        path = Path("/tmp") / f"fleetgcs-px4-block-{self.first}.lock"
        self._lock = path.open("w")
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    self._lock.close()
                    self._lock = None
                    busy = f"PX4 instances {self.instances} busy for {timeout:.0f} s ({path})"
                    raise TimeoutError(busy) from None
                time.sleep(0.5)

    def start(self, lock_timeout: float = 120.0) -> PX4Fleet:
        self._acquire(lock_timeout)
        try:
            bindir = self._bin()
            for index, i in enumerate(self.instances):
                lat, lon, alt = self.home_of(index)
                folder = self.workdir / str(i)
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir(parents=True)
                env = {
                    **os.environ,
                    "PATH": f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}",
                    "PX4_SIM_MODEL": "sihsim_quadx",
                    "PX4_HOME_LAT": f"{lat:.7f}",
                    "PX4_HOME_LON": f"{lon:.7f}",
                    "PX4_HOME_ALT": f"{alt:.2f}",
                    **{f"PX4_PARAM_{k}": v for k, v in self.params.items()},
                }
                if self.speed_factor != 1.0:
                    env["PX4_SIM_SPEED_FACTOR"] = f"{self.speed_factor:g}"
                with (folder / "px4.log").open("wb") as log:
                    self.procs.append(
                        subprocess.Popen(
                            [*self._command(bindir), "-i", str(i), "-d", str(self.px4 / "etc")],
                            cwd=folder,
                            env=env,
                            stdin=subprocess.DEVNULL,
                            stdout=log,
                            stderr=subprocess.STDOUT,
                            preexec_fn=lambda: _preexec(self.nice),
                        )
                    )
            time.sleep(1.0)
            dead = [i for i, p in zip(self.instances, self.procs, strict=True) if p.poll() is not None]
            if dead:
                raise RuntimeError(f"PX4 instance(s) {dead} exited at boot: {self.log_tail(dead[0])}")
        except BaseException:
            self.stop()
            raise
        return self

    def log_tail(self, instance: int, lines: int = 5) -> str:
        try:
            text = (self.workdir / str(instance) / "px4.log").read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return " | ".join(text[-lines:]) or "(empty log)"

    def failsafe_flags(self, instance: int, timeout: float = 5.0) -> list[str]:
        """The conditions of PX4's failsafe state machine that hold now (its ``failsafe_flags`` topic, read
        with ``listener`` through the instance's socket), without the three that hold in every flight
        here (no mission uploaded, no offboard stream, no RC: PX4 ignores the last since it armed
        without one). PX4 says only "Failsafe activated" on MAVLink; its reason is an event that
        pymavlink does not decode, so a test reads this instead (bounded; [] if it cannot be read)."""
        listener = self.workdir / "bin" / "px4-listener"
        try:
            out = subprocess.run(
                [str(listener), "--instance", str(instance), "failsafe_flags"],
                capture_output=True,
                text=True,
                timeout=timeout,
                cwd=self.workdir,
                check=False,
            ).stdout
        except (OSError, subprocess.TimeoutExpired) as e:
            return [f"(listener failed: {e})"]
        usual = {"auto_mission_missing", "offboard_control_signal_lost", "manual_control_signal_lost"}
        flags = []
        for line in out.splitlines():
            key, _, value = line.strip().partition(": ")
            skip = key in usual or key.startswith(("mode_req", "timestamp", "TOPIC"))
            if value not in ("False", "0", "") and not skip:
                flags.append(f"{key}={value}" if value != "True" else key)
        return flags

    def alive(self) -> bool:
        return bool(self.procs) and all(p.poll() is None for p in self.procs)

    def stop(self) -> None:
        """SIGINT (PX4's clean shutdown), SIGKILL after 5 s; then release the instance block."""
        for p in self.procs:
            if p.poll() is None:
                with contextlib.suppress(OSError):
                    p.send_signal(2)
        deadline = time.monotonic() + 5.0
        for p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(2.0)
        self.procs.clear()
        if self._lock is not None:
            self._lock.close()
            self._lock = None
