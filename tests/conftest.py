"""Suite-wide collection rules.

The suite runs on two pytest-xdist workers (``scripts/test``). The flight scenarios, the real
ArduCopter runs and the packaging test (which builds wheels and venvs) are the CPU-heavy ones:
they share one worker (``xdist_group("heavy")`` with ``--dist loadgroup``), so no two of them
compete for the same two cores while their vehicles fly in accelerated time; everything else is
spread over the other worker as it frees up.

The real PX4 runs (``tests/px4``) go to one group per agent backend (``px4-mavlink``, ``px4-mavsdk``):
each backend's modules share one worker and its own block of PX4 instance ids, and the two backends
run side by side. PX4 itself runs at ``PX4_SIM_SPEED_FACTOR`` and niced, so it is not "heavy".
"""

from __future__ import annotations

from pathlib import Path

import pytest

HEAVY = ("scenarios", "ardupilot", "packaging")


@pytest.hookimpl(tryfirst=True)  # before xdist's loadgroup renames the items by their group
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    tests_dir = Path(__file__).parent
    for item in items:
        parts = Path(item.path).relative_to(tests_dir).parts
        if parts and parts[0] in HEAVY:
            item.add_marker(pytest.mark.xdist_group("heavy"))
        elif parts and parts[0] == "px4":
            callspec = getattr(item, "callspec", None)
            backend = callspec.params.get("rig", "mavlink") if callspec is not None else "mavlink"
            item.add_marker(pytest.mark.xdist_group(f"px4-{backend}"))
