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
    run.add_argument("--vehicles", "-n", type=int, default=1, help="number of vehicles (1..250)")
    run.add_argument(
        "--home",
        type=lambda s: _floats(s, 2, 3, "--home"),
        default=None,
        help="LAT,LON[,ALT_AMSL] of vehicle 0 (default ArduPilot's CMAC)",
    )
    run.add_argument(
        "--base-port", type=int, default=5760, help="vehicle i listens on BASE+10*i; 0 = ephemeral ports"
    )
    run.add_argument("--transport", choices=("tcp", "udp"), default="tcp")
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
        help="run real arducopter binaries instead (PATH or $ARDUPILOT_SITL)",
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


def main(argv: list[str] | None = None) -> int:
    """Console entry point (``sitl = "sitl.cli:main"``)."""
    args = build_parser().parse_args(argv)
    stop = _StopSignal()
    from sitl.fleet import DEFAULT_HOME, FleetConfig, SimFleet

    home = args.home if args.home is not None else DEFAULT_HOME
    if args.ardupilot is not None:
        from sitl.ardupilot import ArduPilotFleet, find_binary

        binary = find_binary(args.ardupilot or None)
        if binary is None:
            print("sitl: no arducopter binary (give --ardupilot PATH or set ARDUPILOT_SITL)", file=sys.stderr)
            return 2
        apf = ArduPilotFleet(binary, args.vehicles, home, args.spacing, args.speedup or 1.0)
        try:
            apf.start()
        except RuntimeError as exc:
            print(f"sitl: {exc}", file=sys.stderr)
            return 1
        print("SITL READY " + " ".join(apf.endpoints), flush=True)
        try:
            stop.wait(apf.alive)
        finally:
            apf.stop()
        return 0

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
    )
    try:
        fleet = SimFleet(cfg)
        fleet.start()
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"sitl: {exc}", file=sys.stderr)
        return 2
    print("SITL READY " + " ".join(fleet.endpoints), flush=True)
    try:
        stop.wait(lambda: fleet.running)
    finally:
        fleet.stop()
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
