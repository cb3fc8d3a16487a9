"""``sitl run``: start the embedded multi-vehicle simulator (or real ArduCopter SITL) from the shell.

Prints exactly one line ``SITL READY <endpoint> ...`` on stdout once every endpoint listens, then runs
until SIGINT/SIGTERM. Diagnostics go to stderr.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType

from protocol.geo import allow_negative_coordinates


def _floats(text: str, n_min: int, n_max: int, what: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if not n_min <= len(vals) <= n_max:
        raise argparse.ArgumentTypeError(f"{what}: expected {n_min}..{n_max} numbers, got {text!r}")
    return vals


def _param(text: str) -> tuple[str, float]:
    name, _, value = text.partition("=")
    try:
        return name.strip().upper(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--param: expected NAME=VALUE, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    """The ``sitl`` argument parser."""
    ap = argparse.ArgumentParser(prog="sitl", description="fleetgcs multi-vehicle MAVLink copter simulator")
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = ap.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run", help="start N simulated copters and serve MAVLink until interrupted")
    allow_negative_coordinates(run)  # --home -35.36,149.16,584
    run.add_argument("--vehicles", "-n", type=int, default=1, help="number of vehicles (1..250)")
    run.add_argument(
        "--home",
        type=lambda s: _floats(s, 2, 3, "--home"),
        default=None,
        help="LAT,LON[,ALT_AMSL] of vehicle 0 (default ArduPilot's CMAC)",
    )
    run.add_argument(
        "--flavour",
        choices=("ardupilot", "px4"),
        default="ardupilot",
        help="autopilot personality: ArduCopter (default) or PX4 v1.16 (UDP links as PX4 SITL's API link)",
    )
    run.add_argument(
        "--base-port",
        type=int,
        default=None,
        help="ardupilot: vehicle i listens on BASE+10*i (default 5760); px4: vehicle i sends to BASE+i and "
        "listens on BASE+40+i (default 14540); 0 = ephemeral ports",
    )
    run.add_argument("--transport", choices=("tcp", "udp"), default=None, help="ardupilot only (default tcp)")
    run.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    run.add_argument(
        "--speedup", type=float, default=1.0, help="sim seconds per wall second (0 = as fast as possible)"
    )
    run.add_argument("--seed", type=int, default=0, help="random seed (wind gusts, GPS noise, path wobble)")
    run.add_argument("--spacing", type=float, default=5.0, help="metres between vehicle homes (east)")
    run.add_argument(
        "--prearm-delay",
        type=float,
        default=3.0,
        help="sim seconds after boot during which arming is refused",
    )
    run.add_argument(
        "--legacy-mission-request",
        action="store_true",
        help="request mission items with MISSION_REQUEST instead of MISSION_REQUEST_INT",
    )
    run.add_argument(
        "--wind",
        type=lambda s: _floats(s, 2, 2, "--wind"),
        default=(0.0, 0.0),
        help="steady wind NORTH,EAST in m/s (direction it blows toward)",
    )
    run.add_argument("--gust", type=float, default=0.0, help="gust standard deviation in m/s")
    run.add_argument("--physics-hz", type=float, default=50.0, help="fixed physics step rate (sim time)")
    run.add_argument(
        "--param",
        type=_param,
        action="append",
        default=[],
        help="parameter override NAME=VALUE (repeatable), e.g. WPNAV_SPEED=800",
    )
    run.add_argument(
        "--fail",
        action="append",
        default=[],
        help="failure injection VEH:KIND@START[+DUR][=VAL], e.g. 1:link_drop@30+10 (repeatable)",
    )
    run.add_argument(
        "--ardupilot",
        nargs="?",
        const="",
        default=None,
        metavar="PATH",
        help="run real arducopter binaries instead (PATH or $ARDUPILOT_SITL); honours --vehicles, "
        "--home, --spacing, --speedup, --base-port, --host, --param, --wind",
    )
    run.add_argument(
        "--pilot-links",
        action="store_true",
        help="a second MAVLink link per vehicle for a pilot's ground station (ArduPilot: SERIAL1, port "
        "P + 10*i + 2); what it sets counts as the pilot's (docs/simulator.md); printed as PILOT LINKS",
    )
    run.add_argument(
        "--keep-logs",
        action="store_true",
        help="--ardupilot: write dataflash logs and keep the instances' scratch directory (path on stderr)",
    )
    return ap


class _StopSignal:
    """SIGINT/SIGTERM catcher, installed *before* the READY line so an early signal still exits cleanly."""

    def __init__(self) -> None:
        self.event = threading.Event()
        signal.signal(signal.SIGINT, self._handler)
        signal.signal(signal.SIGTERM, self._handler)

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        self.event.set()

    def wait(self, alive: Callable[[], bool]) -> None:
        """Block until a signal arrives or ``alive()`` turns false."""
        while not self.event.wait(0.2) and alive():
            pass


def _run_ardupilot(args: argparse.Namespace, home: tuple[float, ...], stop: _StopSignal) -> int:
    """``sitl run --ardupilot``: real arducopter instances behind the same READY contract."""
    from sitl.ardupilot import ArduPilotFleet, find_binary, wind_params

    unsupported = [
        flag
        for flag, used in (
            ("--fail", bool(args.fail)),
            ("--transport udp", args.transport != "tcp"),
            ("--gust", args.gust != 0.0),
            ("--legacy-mission-request", args.legacy_mission_request),
        )
        if used
    ]
    if unsupported:
        print(f"sitl: {', '.join(unsupported)} not supported with --ardupilot", file=sys.stderr)
        return 2
    binary = find_binary(args.ardupilot or None)
    if binary is None:
        print("sitl: no arducopter binary (give --ardupilot PATH or set ARDUPILOT_SITL)", file=sys.stderr)
        return 2
    params = {**wind_params(*args.wind), **dict(args.param)} if any(args.wind) else dict(args.param)
    try:
        apf = ArduPilotFleet(
            binary,
            args.vehicles,
            home,
            args.spacing,
            args.speedup or 1.0,
            base_port=args.base_port,
            host=args.host,
            params=params,
            keep_logs=args.keep_logs,
            pilot_links=args.pilot_links,
        )
    except ValueError as exc:
        print(f"sitl: {exc}", file=sys.stderr)
        return 2
    try:
        apf.start()
    except (RuntimeError, OSError) as exc:
        print(f"sitl: {exc}", file=sys.stderr)
        return 1
    if args.keep_logs:
        print(f"sitl: logs in {apf.workdir}", file=sys.stderr)
    if apf.pilot_endpoints:
        print("PILOT LINKS " + " ".join(apf.pilot_endpoints), flush=True)
    print("SITL READY " + " ".join(apf.endpoints), flush=True)
    try:
        stop.wait(apf.alive)
    finally:
        apf.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    """Console entry point (``sitl = "sitl.cli:main"``)."""
    args = build_parser().parse_args(argv)
    stop = _StopSignal()
    from sitl.fleet import DEFAULT_HOME, PX4_BASE_PORT, PX4_HOME, FleetConfig, SimFleet

    px4 = args.flavour == "px4"
    if px4 and (args.ardupilot is not None or args.transport is not None):
        flag = "--ardupilot" if args.ardupilot is not None else "--transport"
        print(f"sitl: {flag} does not go with --flavour px4 (PX4 SITL links are UDP)", file=sys.stderr)
        return 2
    home = args.home if args.home is not None else (PX4_HOME if px4 else DEFAULT_HOME)
    if args.base_port is None:
        args.base_port = PX4_BASE_PORT if px4 else 5760
    if args.transport is None:
        args.transport = "tcp"
    if args.ardupilot is not None:
        return _run_ardupilot(args, home, stop)

    cfg = FleetConfig(
        vehicles=args.vehicles,
        home=home,
        base_port=args.base_port,
        speedup=args.speedup,
        seed=args.seed,
        transport=args.transport,
        spacing_m=args.spacing,
        prearm_delay_s=args.prearm_delay,
        legacy_mission_request=args.legacy_mission_request,
        wind=(args.wind[0], args.wind[1]),
        gust_mps=args.gust,
        host=args.host,
        physics_hz=args.physics_hz,
        params=dict(args.param),
        failures=list(args.fail),
        flavour=args.flavour,
        pilot_links=args.pilot_links,
    )
    try:
        fleet = SimFleet(cfg)
        fleet.start()
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"sitl: {exc}", file=sys.stderr)
        return 2
    if fleet.pilot_endpoints:
        print("PILOT LINKS " + " ".join(fleet.pilot_endpoints), flush=True)
    print("SITL READY " + " ".join(fleet.endpoints), flush=True)
    try:
        stop.wait(lambda: fleet.running)
    finally:
        fleet.stop()
    if fleet.overruns:
        print(
            f"sitl: fell behind {fleet.overruns} times ({fleet.dropped_sim_s:.1f} sim s dropped); "
            f"speed-up kept {fleet.speedup_kept:.2f}x of {cfg.speedup:g}x",
            file=sys.stderr,
        )
    if fleet.error is not None:
        print(f"sitl: simulation failed: {fleet.error!r}", file=sys.stderr)
        return 1
    return 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fleetgcs")
    except PackageNotFoundError:
        return "unknown (not installed)"


if __name__ == "__main__":
    sys.exit(main())
