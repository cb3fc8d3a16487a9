"""`gcs demo`: fly a synchronized multi-drone survey on the embedded simulator, then summarise."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys
import tempfile
from pathlib import Path
from typing import IO

from gcs.commands.demo_mission import DemoError, DemoOptions, run_demo, summary_table
from protocol.geo import allow_negative_coordinates


def _home(text: str) -> tuple[float, float, float]:
    parts = [float(p) for p in text.split(",")]
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError("--home is LAT,LON[,ALT_AMSL]")
    return (parts[0], parts[1], parts[2] if len(parts) == 3 else 488.0)


def log_to_file(path: Path) -> IO[bytes]:
    """Send this process's logging, and return a handle for the child processes' stderr, to ``path``.

    The status table stays readable: 50-odd INFO lines a run would interleave with it.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    handler = logging.FileHandler(path, mode="a")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    return path.open("ab", buffering=0)  # append: the children's lines and ours never overwrite


def run(args: argparse.Namespace) -> int:
    log: IO[bytes] | None = None
    if not getattr(args, "verbose", False):
        default = (args.data_dir or Path(tempfile.gettempdir())) / "fleetgcs-demo.log"
        log_path = args.log or default
        log = log_to_file(log_path)
        print(f"logs (gcs demo --verbose: on the terminal instead):\n  {log_path}", flush=True)
    with contextlib.closing(log) if log is not None else contextlib.nullcontext():
        return _run(args, log)


def _run(args: argparse.Namespace, log: IO[bytes] | None) -> int:
    options = DemoOptions(
        drones=args.drones,
        home=args.home,
        speedup=args.speedup,
        seed=args.seed,
        pattern=args.pattern,
        division=args.division,
        altitude_m=args.alt,
        swath_m=args.swath,
        speed_mps=args.speed,
        timeout_s=args.timeout,
        data_dir=args.data_dir,
        http=args.http,
        ardupilot=args.ardupilot,
        log=log,
    )
    try:
        result = asyncio.run(run_demo(options))
    except DemoError as exc:
        print(f"gcs demo: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # planning rejected the options (area, capability...)
        print(f"gcs demo: cannot plan the mission: {exc}", file=sys.stderr)
        return 2
    print(summary_table(result))
    return 0 if result.ok else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="fly a multi-drone mission on the embedded simulator")
    allow_negative_coordinates(parser)  # --home -35.36,149.16
    parser.add_argument(
        "--drones", type=int, default=3, choices=range(1, 51), metavar="1..50", help="simulated drones (3)"
    )
    parser.add_argument("--home", type=_home, default=(47.397742, 8.545594, 488.0), help="LAT,LON[,ALT]")
    parser.add_argument(
        "--speedup", type=float, default=4.0, help="simulation speed-up (default %(default)s)"
    )
    parser.add_argument("--seed", type=int, default=1, help="the simulator's random seed (wind, noise)")
    parser.add_argument(
        "--pattern",
        default="zigzag",
        choices=["zigzag", "spiral", "segmented", "curved"],
        help="survey pattern (docs/planning.md)",
    )
    parser.add_argument(
        "--division",
        default="region",
        choices=["path", "region", "partition"],
        help="how the area is shared among the drones (docs/planning.md)",
    )
    parser.add_argument("--alt", type=float, default=12.0, help="survey altitude, m")
    parser.add_argument("--swath", type=float, default=14.0, help="sensor swath, m")
    parser.add_argument("--speed", type=float, default=6.0, help="survey speed, m/s")
    parser.add_argument("--timeout", type=float, default=600.0, help="abort the mission after this many s")
    parser.add_argument("--data-dir", type=Path, help="keep the daemon database here (default: temporary)")
    parser.add_argument("--http", help="also serve the HTTP API on HOST:PORT")
    parser.add_argument(
        "--log",
        type=Path,
        help="write the daemon's, agents' and simulator's logs here "
        "(default: DATA_DIR/fleetgcs-demo.log, or fleetgcs-demo.log in the temporary directory)",
    )
    parser.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        default=argparse.SUPPRESS,
        help="logs on the terminal, mixed with the status table, instead of in the log file",
    )
    parser.add_argument(
        "--ardupilot",
        nargs="?",
        const="",
        default=None,
        metavar="PATH",
        help="fly on real ArduCopter SITL (the arducopter binary; default $ARDUPILOT_SITL or PATH)",
    )
    parser.set_defaults(run=run)
