"""`gcs agents`: the fleet as the daemon sees it; `gcs agents retire ID` takes a ghost off the list."""

from __future__ import annotations

import argparse

from gcs.commands._api import CommandError, api_arguments, call
from gcs.http.models import AgentView


def _row(agent: AgentView, clustered: bool = False) -> str:
    status = agent.status
    link = "up" if agent.connected else ("lost" if agent.lost else "down")
    battery = status.battery.pct if status is not None else None
    position = getattr(status, "position", None)  # absent before the first GPS fix
    alt_m = round(position.alt_rel, 1) + 0.0 if position is not None else None  # + 0.0: no "-0.0"
    alt = f"{alt_m:6.1f}" if alt_m is not None else f"{'-':>6}"
    step = status.step if status is not None and status.step >= 0 else "-"
    control = "-"
    if status is not None and status.pilot:
        control = f"PILOT {status.pilot}"  # the daemon sends it nothing until the pilot hands back
    elif status is not None and status.failsafe:
        control = "failsafe"
    elif agent.held:
        control = f"held: {agent.held}"
    elif status is not None and status.paused:
        control = "held"
    daemon = f"{agent.daemon or '-':12} " if clustered else ""  # where its link is (cluster mode)
    return (
        f"{agent.cid:>4} {agent.identity:16} {link:5} {status.mode if status else '-':9} "
        f"{status.armed if status else False!s:5} {battery if battery is not None else '-':>5} "
        f"{alt} {step:>4} {daemon}{control}"
    )


def run_list(args: argparse.Namespace) -> int:
    agents = call(args, lambda client: client.agents(), token=False)
    clustered = any(agent.daemon for agent in agents)  # a cluster daemon names each link's holder
    head = f"{'cid':>4} {'identity':16} {'link':5} {'mode':9} {'armed':5} {'batt%':>5} {'alt':>6} {'step':>4}"
    print(f"{head} {'daemon':12} control" if clustered else f"{head} control")
    for agent in agents:
        print(_row(agent, clustered))
    return 0


def run_retire(args: argparse.Namespace) -> int:
    retired = call(args, lambda client: client.retire(args.identity))
    print(f"{retired.identity} (cid {retired.cid}) retired: off the fleet list; its cid stays reserved")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.action == "retire":
        if not args.identity:
            raise CommandError("give the identity: gcs agents retire ID")
        return run_retire(args)
    if args.identity:
        raise CommandError(f"unexpected {args.identity!r}: gcs agents [list | retire ID]")
    return run_list(args)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "agents", help="list agents and their latest status (retire ID: take a ghost off the list)"
    )
    parser.add_argument(
        "action", nargs="?", choices=["list", "retire"], default="list", help="list (default) or retire ID"
    )
    parser.add_argument("identity", nargs="?", help="retire: the agent to take off the fleet list")
    api_arguments(parser)
    parser.set_defaults(run=run)
