"""`gcs` command line: each module in ``gcs.commands`` registers one subcommand.

Failures an operator can act on (a missing file, the daemon down, a refused call, Ctrl-C) end
in one line on stderr and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
from collections.abc import Callable, Sequence

from protocol.settings_file import package_version

Runner = Callable[[argparse.Namespace], int]
GCS_EXTRA_HINT = "the ground station is not installed here: pip install 'fleetgcs[gcs]'"


def build_parser() -> argparse.ArgumentParser:
    import gcs.commands

    parser = argparse.ArgumentParser(prog="gcs", description="fleetgcs ground control station")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_info in sorted(pkgutil.iter_modules(gcs.commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"gcs.commands.{module_info.name}")
        register = getattr(module, "register", None)
        if callable(register):
            register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:
        parser = build_parser()
    except ModuleNotFoundError as exc:  # an agent-only install (pip install fleetgcs) has no gcs extra
        print(f"gcs: {GCS_EXTRA_HINT} (missing module {exc.name!r})", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    logging.getLogger("httpx").setLevel(logging.WARNING)
    runner: Runner = args.run
    return run_reporting_errors(f"gcs {args.command}", lambda: runner(args))


def _quiet_stdout() -> None:
    """Point stdout at /dev/null, so flushing it at exit raises no second BrokenPipeError."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def run_reporting_errors(prog: str, body: Callable[[], int]) -> int:
    """``body()``, with the errors an operator can act on turned into one line on stderr."""
    import httpx

    from gcs.commands._api import CommandError

    try:
        return body()
    except BrokenPipeError:  # `gcs mission list | head`: the reader has what it wanted
        _quiet_stdout()
        return 0
    except KeyboardInterrupt:
        print(f"\n{prog}: interrupted", file=sys.stderr)
        return 130
    except CommandError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return exc.code
    except httpx.TransportError as exc:
        print(f"{prog}: cannot reach the daemon ({exc or type(exc).__name__})", file=sys.stderr)
        return 3
    except httpx.HTTPStatusError as exc:
        print(f"{prog}: HTTP {exc.response.status_code}: {exc.response.text[:300]}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.filename is None:
            raise
        print(f"{prog}: cannot use {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
