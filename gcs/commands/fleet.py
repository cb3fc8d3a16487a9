"""`gcs fleet rtl|land|hold|resume [--drone ID ...]`: fleet commands from the shell, as in MAVProxy.

Calls the daemon's ``/api/v1/fleet/{command}``: RTL and land abort the missions involved;
hold stops the drones where they are with their queues kept, resume continues them.
"""

from __future__ import annotations

import argparse
import typing

from gcs.commands._api import CommandError, api_arguments, call

COMMANDS = ("rtl", "land", "hold", "resume")
Command = typing.Literal["rtl", "land", "hold", "resume"]


def run(args: argparse.Namespace) -> int:
    command: Command = args.fleet_command
    drones: list[str] | None = args.drone
    result = call(args, lambda client: client.command_fleet(command, drones, reason="gcs fleet (shell)"))
    if not result.delivered:
        raise CommandError(
            f"{command} reached no drone: "
            + ("none of " + ", ".join(drones) + " is connected" if drones else "no drone is connected"),
            1,
        )
    print(f"{command} sent to {', '.join(result.delivered)}")
    if result.aborted_missions:
        print(f"aborted missions: {', '.join(result.aborted_missions)}")
    missing = sorted(set(drones or []) - set(result.delivered))
    if missing:
        raise CommandError(f"not delivered to {', '.join(missing)} (not connected)", 1)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("fleet", help="rtl | land | hold | resume the whole fleet or some drones")
    parser.add_argument(
        "fleet_command",
        choices=COMMANDS,
        metavar="{rtl,land,hold,resume}",
        help="rtl/land abort the missions involved; hold keeps the queue; resume continues",
    )
    parser.add_argument(
        "--drone", action="append", metavar="ID", help="only this drone (repeat for more; default all)"
    )
    api_arguments(parser)
    parser.set_defaults(run=run)
