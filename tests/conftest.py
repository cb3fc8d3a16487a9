"""Suite-wide collection rules.

The suite runs on three pytest-xdist workers on two cores (``scripts/test``), each test sent to
whichever worker is free. The flight scenarios and the packaging test are not grouped:
kept on one worker (the ``heavy`` group, in force for the first time with the scheduler below)
they ran one after the other for 10+ minutes while the other worker idled, and the suite took 19
minutes instead of 12; side by side they wait on accelerated simulators more than they compute.

The real PX4 runs (``tests/px4``) go to one group per agent backend (``px4-mavlink``, ``px4-mavsdk``):
each backend's modules share one worker and its own block of PX4 instance ids, and the two backends
run side by side. PX4 itself runs at ``PX4_SIM_SPEED_FACTOR`` and niced, so it is not "heavy".

The real ArduCopter modules (``tests/ardupilot``, parametrized over our simulator and ArduCopter) go to
one group per module: its rigs boot once (not once per worker that draws one of its tests) and its tests
run in file order, which the module relies on (the pilot's takeover is last: it ends by the operator's
release). Spread one by one over three workers, a run failed the pilot's test twice in a row (its drone
never got 30 m into its leg), with the module's order and boots no longer what it was written for.

The groups are put into effect by our own scheduler (:func:`pytest_xdist_make_scheduler`), from the
node ids: pytest-xdist 3.8 marks a grouped test by appending ``@group`` to ``item._nodeid``, which
pytest 9 no longer reads (the node id is ``item._id``), so its ``--dist loadgroup`` silently spread
every group over both workers (each worker then booted its own PX4 fleet for one backend).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

# Folders whose tests fly on a wall clock (accelerated simulators, real ArduCopter/PX4, NATS, browsers,
# console scripts as processes) get one rerun: on a shared two-core machine each of them was seen to
# fail once in a full run and never alone (docs/testing.md, "Reruns"). A second failure fails the suite,
# and `-rR` style summaries still count every rerun ("N rerun"), so a flake stays visible.
RERUN_ONCE = frozenset({"scenarios", "ardupilot", "px4", "web", "cli", "demo", "cluster", "faults"})

_BACKEND = re.compile(r"\[(?:[^\]]*-)?(mavlink|mavsdk)(?:-[^\]]*)?\]$")


def xdist_group_of(nodeid: str) -> str | None:
    """The group of a test from its node id (``tests/px4/test_x.py::test_y[mavsdk]``), or None."""
    if "@" in nodeid:  # an xdist that did mark it (a fixed pytest/xdist pair)
        return nodeid.rsplit("@", 1)[1]
    path = nodeid.split("::", 1)[0]
    parts = Path(path).parts
    top = parts[parts.index("tests") + 1] if "tests" in parts[:-1] else (parts[0] if parts else "")
    if top == "px4":
        backend = _BACKEND.search(nodeid)
        return f"px4-{backend.group(1)}" if backend else None
    if top == "ardupilot" and "[" in nodeid:  # a flight on a module's rig
        return f"ardupilot-{Path(path).stem}"
    return None


@pytest.hookimpl(optionalhook=True)  # an xdist hook: pytest without xdist must not reject it
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup`` as meant: each group's tests on one worker, the rest spread one by one."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_group_of(nodeid) or nodeid

    return GroupScheduling(config, log)


@pytest.hookimpl(tryfirst=True)  # before xdist's loadgroup renames the items by their group
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    tests_dir = Path(__file__).parent
    for item in items:
        parts = Path(item.path).relative_to(tests_dir).parts
        if parts and parts[0] in RERUN_ONCE and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=1))
        if parts and parts[0] == "px4":
            callspec = getattr(item, "callspec", None)
            backend = callspec.params.get("rig") if callspec is not None else None
            if backend is not None:  # a flight on PX4; the rest of tests/px4 needs no PX4
                item.add_marker(pytest.mark.xdist_group(f"px4-{backend}"))
