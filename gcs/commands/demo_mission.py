"""The main job, end to end on one machine: daemon + simulated vehicles + agents + a planned mission.

The daemon runs in this process. The simulator (`python -m sitl run`) and the agents
(`python -m agent run`), one per vehicle, are separate processes. They talk real TCP (our
protocol) and real MAVLink (simulator <-> agents), like a field deployment on one laptop.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import secrets
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING

from gcs.cooperation.config import EnergyConfig
from gcs.cooperation.energy import EnergyPrediction, predict_plan_energy
from gcs.core.config import DaemonConfig
from gcs.link.beacon import loopback_beacon_address
from gcs.observe.flight_recorder import FlightRecorder
from gcs.planning.areas import area_from_latlon
from gcs.planning.camera import spacing_from_swath
from gcs.planning.division import DroneSpec
from gcs.planning.planner import PlanConfig, plan_search
from protocol.actions import Waypoints
from protocol.geo import offset_latlon
from protocol.packets import StatusReport
from protocol.taskfile import TaskFile

if TYPE_CHECKING:  # the daemon is imported when the demo runs, not by every `gcs` command's start
    from gcs.core.daemon import Daemon
    from gcs.missions.model import MissionProgress

HOME_SPACING_M = 6.0  # between simulated vehicles' homes: more than the collision margin


@dataclass
class DemoOptions:
    drones: int = 3
    home: tuple[float, float, float] = (47.397742, 8.545594, 488.0)
    speedup: float = 4.0
    seed: int = 1
    pattern: str = "zigzag"
    division: str = "region"
    area_m: tuple[float, float] = (90.0, 60.0)  # east x north extent of the survey rectangle
    altitude_m: float = 12.0
    swath_m: float = 14.0
    speed_mps: float = 6.0
    timeout_s: float = 600.0
    data_dir: Path | None = None
    http: str | None = None
    quiet: bool = False
    ardupilot: str | None = None  # fly on real ArduCopter SITL: the binary ("" = $ARDUPILOT_SITL / PATH)
    log: IO[bytes] | None = None  # the simulator's and agents' logs go here (None: to this stderr)


@dataclass
class DemoResult:
    ok: bool
    mission: MissionProgress | None
    recorder: FlightRecorder
    landed: dict[str, bool]
    message: str
    mission_wall_s: float = 0.0  # from submit (pre-flight wait included) to the mission's end
    predicted: dict[str, EnergyPrediction] = field(default_factory=dict)  # before take-off
    speedup: float = 1.0  # asked of the simulator
    beacons: int = 0  # barrier releases announced by UDP release beacon (protocol/beacon.py)


class DemoError(RuntimeError):
    """The demo could not run (a process failed to start, agents did not join...)."""


WIDTH = 100  # the demo's output fits a 100-column terminal


def _say(options: DemoOptions, text: str) -> None:
    if not options.quiet:
        print(fit(text), flush=True)


def fit(text: str, width: int = WIDTH) -> str:
    """``text`` with every line wrapped to ``width`` columns (continuations indented)."""
    out: list[str] = []
    for line in text.splitlines():
        if len(line) <= width:
            out.append(line)
        else:
            out += textwrap.wrap(line, width, subsequent_indent="    ", break_on_hyphens=False)
    return "\n".join(out)


def survey_area(options: DemoOptions) -> list[tuple[float, float]]:
    """A rectangle starting 15 m north of home."""
    lat, lon, _ = options.home
    east, north = options.area_m
    corners = [(15.0, -10.0), (15.0, east - 10.0), (15.0 + north, east - 10.0), (15.0 + north, -10.0)]
    return [offset_latlon(lat, lon, n, e) for n, e in corners]


def vehicle_homes(options: DemoOptions) -> list[tuple[float, float]]:
    """Where the simulator puts each vehicle: ``HOME_SPACING_M`` apart, eastwards."""
    lat, lon, _ = options.home
    return [offset_latlon(lat, lon, 0.0, HOME_SPACING_M * i) for i in range(options.drones)]


def plan_demo_mission(
    options: DemoOptions, names: list[str]
) -> tuple[TaskFile, list[list[tuple[float, float]]]]:
    area = area_from_latlon(survey_area(options), name="demo-area")
    drones = [DroneSpec(name=n, speed_mps=options.speed_mps, endurance_s=900.0) for n in names]
    config = PlanConfig(
        pattern=options.pattern,  # type: ignore[arg-type]
        division=options.division,  # type: ignore[arg-type]
        name="demo",
        transit_alt_step=3.0,  # transit and return legs at different altitudes per drone
        return_mode="land_home",  # each back to its own launch point, not all onto one RTL spot
    )
    plan = plan_search(
        area,
        drones,
        spacing_from_swath(options.swath_m, options.altitude_m),
        config,
        home_latlon=(options.home[0], options.home[1]),
        speed=options.speed_mps,
        agent_names=names,
        homes_latlon=vehicle_homes(options),
    )
    return plan.taskfile, plan.paths_latlon


def simulator_command(options: DemoOptions) -> list[str]:
    """``sitl run`` for the demo: our simulator, or real ArduCopter SITL with ``options.ardupilot``."""
    cmd = [sys.executable, "-m", "sitl", "run", "--vehicles", str(options.drones)]
    cmd += ["--home=" + ",".join(str(v) for v in options.home), "--base-port", "0"]
    cmd += ["--speedup", str(options.speedup), "--spacing", str(HOME_SPACING_M)]
    if options.ardupilot is not None:
        return [*cmd, "--ardupilot", *([options.ardupilot] if options.ardupilot else [])]
    return [*cmd, "--seed", str(options.seed)]


async def _start_simulator(options: DemoOptions) -> tuple[asyncio.subprocess.Process, list[str]]:
    process = await asyncio.create_subprocess_exec(
        *simulator_command(options),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.DEVNULL if options.quiet else options.log,
    )
    assert process.stdout is not None
    try:
        async with asyncio.timeout(30):
            while True:
                line = (await process.stdout.readline()).decode()
                if not line:
                    raise DemoError(f"the simulator exited with {await process.wait()} before it was ready")
                if line.startswith("SITL READY"):
                    return process, line.split()[2:]
    except TimeoutError:
        process.kill()
        raise DemoError("the simulator did not report READY within 30 s") from None


async def _start_agents(
    endpoints: list[str],
    names: list[str],
    port: int,
    key_file: Path,
    quiet: bool,
    beacon: str | None = None,
    log: IO[bytes] | None = None,
) -> list[asyncio.subprocess.Process]:
    processes = []
    for name, endpoint in zip(names, endpoints, strict=True):
        processes.append(
            await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "agent",
                "run",
                "--id",
                name,
                "--gcs",
                f"127.0.0.1:{port}",
                "--autopilot",
                endpoint,
                "--key-file",
                str(key_file),
                "--max-speed",
                "10",
                *(["--release-beacon", beacon] if beacon else []),
                stderr=asyncio.subprocess.DEVNULL if quiet else log,
            )
        )
    return processes


async def _stop(processes: list[asyncio.subprocess.Process]) -> None:
    for process in processes:
        if process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                process.terminate()
    for process in processes:
        try:
            await asyncio.wait_for(process.wait(), 10)
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            await process.wait()


@dataclass(frozen=True)
class DroneRow:
    """One drone's line of the demo's status table (None: not known yet)."""

    name: str
    mode: str | None
    step: int | None
    sync: int | None
    alt_m: float | None
    battery_pct: float | None


def _cell(value: float | None, digits: int = 1) -> str:
    """A number for the table: "-" when unknown, never "-0.0" nor "nan"."""
    if value is None or not math.isfinite(value):
        return "-"
    return f"{round(value, digits) + 0.0:.{digits}f}"


def status_table(elapsed_s: float, released: str, rows: list[DroneRow]) -> str:
    """The demo's status: a header line, then one line per drone (fits 100 columns)."""
    lines = [
        f"t+{elapsed_s:4.0f} s  barriers released {released}",
        f"  {'drone':16} {'mode':10} {'step':>4} {'sync':>4} {'alt m':>6} {'batt %':>6}",
    ]
    for r in rows:
        step = str(r.step) if r.step is not None and r.step >= 0 else "-"
        sync = str(r.sync) if r.sync is not None else "-"
        lines.append(
            f"  {r.name[:16]:16} {(r.mode or '-')[:10]:10} {step:>4} {sync:>4} "
            f"{_cell(r.alt_m):>6} {_cell(r.battery_pct):>6}"
        )
    return "\n".join(lines)


def _drone_rows(daemon: Daemon, names: list[str]) -> list[DroneRow]:
    rows = []
    for name in names:
        session = daemon.agents.sessions.get(name)
        status = session.status if session else None
        if status is None:
            rows.append(DroneRow(name, None, None, None, None, None))
            continue
        alt = status.position.alt_rel if status.position else None
        rows.append(DroneRow(name, status.mode, status.step, status.waiting_sync, alt, status.battery.pct))
    return rows


def _released(daemon: Daemon, mission_id: str) -> str:
    progress = daemon.missions.progress(mission_id)
    return f"{len(progress.released_steps)}/{len(progress.sync_steps)}" if progress else "?"


async def run_demo(options: DemoOptions) -> DemoResult:
    from gcs.core.daemon import Daemon

    names = [f"drone-{i + 1}" for i in range(options.drones)]
    task, paths = plan_demo_mission(options, names)  # plan first: a bad option fails before anything starts
    temp = None if options.data_dir else tempfile.TemporaryDirectory(prefix="fleetgcs-demo-")
    data_dir = options.data_dir or Path(temp.name)  # type: ignore[union-attr]
    key_hex = secrets.token_hex(32)
    beacon = loopback_beacon_address()  # barrier releases by one datagram, then TCP (docs/protocol.md)
    key_file = data_dir / "fleet.key"
    data_dir.mkdir(parents=True, exist_ok=True)
    key_file.write_text(key_hex + "\n")
    os.chmod(key_file, 0o600)
    http_host, http_port = (
        (options.http.rsplit(":", 1)[0], int(options.http.rsplit(":", 1)[1])) if options.http else (None, 0)
    )
    daemon = Daemon(
        DaemonConfig(
            listen_port=0,
            http_host=http_host,
            http_port=http_port,
            data_dir=data_dir,
            fleet_key_hex=key_hex,
            status_period_s=0.2,
            release_beacon=beacon,
        )
    )
    recorder = FlightRecorder(time_scale=options.speedup)
    predicted = predict_plan_energy(  # the daemon's pre-flight estimate, for the summary
        {p.label: list(p.actions) for p in task.plans},
        {n: (h[0], h[1], 0.0) for n, h in zip(names, vehicle_homes(options), strict=True)},
        EnergyConfig(speed_mps=options.speed_mps),
    )
    for plan, path in zip(task.plans, paths, strict=True):
        survey_steps = {a.step for a in plan.actions if isinstance(a, Waypoints)}
        recorder.set_plan(plan.label, path, survey_steps)

    async def record(session: object, status: StatusReport) -> None:
        recorder.add(session.identity, status)  # type: ignore[attr-defined]

    daemon.agents.on_status.append(record)
    await daemon.start()
    simulator: list[asyncio.subprocess.Process] = []
    agents: list[asyncio.subprocess.Process] = []
    try:
        kind = "ArduCopter SITL" if options.ardupilot is not None else "simulated"
        _say(options, f"daemon on 127.0.0.1:{daemon.listen_port}; starting {options.drones} {kind} vehicles")
        sim_process, endpoints = await _start_simulator(options)
        simulator.append(sim_process)
        agents += await _start_agents(
            endpoints, names, daemon.listen_port, key_file, options.quiet, beacon, options.log
        )
        deadline = time.monotonic() + 60
        while not all(daemon.agents.session(n) is not None for n in names):
            if time.monotonic() > deadline:
                raise DemoError(f"agents did not all join within 60 s ({daemon.agents.sessions.keys()})")
            await asyncio.sleep(0.2)
        # Submitted at once: the daemon's pre-flight check waits for every vehicle's first fix.
        _say(
            options,
            f"{len(names)} agents joined; mission '{task.name}' with sync steps {task.plans[0].sync_steps()}",
        )
        submitted = time.monotonic()
        mission_id = await daemon.missions.submit(task)
        deadline = time.monotonic() + options.timeout_s
        last_print, last_key = 0.0, None
        while mission_id in daemon.missions.active and time.monotonic() < deadline:
            now = time.monotonic()
            rows, released = _drone_rows(daemon, names), _released(daemon, mission_id)
            key = (released, [(r.mode, r.step, r.sync) for r in rows])
            # a table when a drone's mode, step or sync changes (at most 1 a second), else every 15 s
            if (key != last_key and now - last_print >= 1.0) or now - last_print >= 15.0:
                _say(options, status_table(now - submitted, released, rows))
                last_print, last_key = now, key
            await asyncio.sleep(0.1)
        if mission_id in daemon.missions.active:
            await daemon.missions.abort(mission_id, f"demo timeout after {options.timeout_s:.0f} s")
        mission_wall_s = time.monotonic() - submitted
        settle = time.monotonic() + 60
        while time.monotonic() < settle and not all(
            (r := recorder.records.get(n)) is not None and r.landed and not r.armed for n in names
        ):
            await asyncio.sleep(0.2)
        progress = daemon.missions.progress(mission_id)
        landed = {n: bool((r := recorder.records.get(n)) and r.landed and not r.armed) for n in names}
        ok = progress is not None and progress.state == "completed" and all(landed.values())
        message = progress.result if progress and progress.result else "no result"
        beacons = daemon.missions.beacon.sent if daemon.missions.beacon is not None else 0
        return DemoResult(
            ok, progress, recorder, landed, message, mission_wall_s, predicted, options.speedup, beacons
        )
    finally:
        await _stop(agents)  # agents first, so none sees its autopilot vanish
        await _stop(simulator)
        await daemon.stop()
        if temp is not None:
            temp.cleanup()


def summary_table(result: DemoResult) -> str:
    lines = [
        f"{'drone':10} {'landed':6} {'dist m':>8} {'air s':>7} {'energy Wh':>9} {'batt used %':>11} "
        f"{'max path err m':>14}"
    ]
    for name, record in sorted(result.recorder.records.items()):
        used = record.battery_used_pct if record.battery_used_pct is not None else float("nan")
        lines.append(
            f"{name:10} {'yes' if result.landed.get(name) else 'NO':6} {record.distance_m:8.1f} "
            f"{record.airborne_s:7.1f} {record.energy_wh:9.2f} {used:11.1f} "
            f"{record.max_path_error_m:14.2f}"
        )
    if result.predicted:
        lines.append("predicted before take-off (energy/vehicle time):")
        lines += [
            f"  {name:10} {p.energy_wh:.2f} Wh/{p.time_s:.0f} s"
            for name, p in sorted(result.predicted.items())
        ]
    kept = [k for r in result.recorder.records.values() if (k := r.speedup_kept) is not None]
    if kept:
        worst = min(kept)
        note = (
            "kept"
            if worst >= 0.9 * result.speedup
            else "NOT kept: the host was too slow;\n    times and energy above are on the vehicle clock"
        )
        lines.append(f"simulator speed-up: {worst:.2f}x of {result.speedup:g}x asked, {note}")
    else:
        lines.append("vehicle clock not reported: times and energy above are wall time x speed-up")
    if result.mission is not None:
        lines.append(
            f"barriers released: {len(result.mission.released_steps)}, "
            f"announced by UDP release beacon: {result.beacons} (each also sent over TCP)"
        )
    state = result.mission.state if result.mission else "unknown"
    lines.append(f"mission: {state} ({result.message}); result: {'SUCCESS' if result.ok else 'FAILURE'}")
    return fit("\n".join(lines))
