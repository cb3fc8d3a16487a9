"""One rig per simulator per module: ``rig`` is parametrized over our simulator and real ArduCopter.

Real ArduCopter SITL on a loaded 2-core machine can latch an internal error (its scheduler overran) and
then refuses every arm until reboot. A test that failed on such a rig fails as
:class:`LatchedInternalError` (its rerun, as for every real-autopilot test, is in tests/conftest.py); before
any test the rig reboots a fleet that latched one, so the rerun flies a fresh ArduCopter."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from tests.ardupilot.binary import SKIP_REASON, ardupilot_binary
from tests.ardupilot.rig import LatchedInternalError, Rig

log = logging.getLogger("tests.ardupilot")


@pytest.fixture(scope="module", params=["ours", "arducopter"])
def rig(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    simulator = str(request.param)
    binary = ardupilot_binary()
    if simulator == "arducopter" and binary is None:
        pytest.skip(SKIP_REASON)
    fleet = Rig(simulator, binary, tmp_path_factory.mktemp(f"rig-{simulator}")).start()
    try:
        yield fleet
    finally:
        fleet.stop()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> object:
    """A failure on a fleet that latched an internal error is raised as :class:`LatchedInternalError`."""
    try:
        return (yield)
    except Exception as failure:
        rig = getattr(item, "funcargs", {}).get("rig")
        latched = rig.latched_internal_error() if isinstance(rig, Rig) else None
        if latched:
            raise LatchedInternalError(latched) from failure
        raise


@pytest.fixture(autouse=True)
def rebooted_if_latched(request: pytest.FixtureRequest) -> None:
    """Reboot an ArduCopter fleet that latched an internal error before the next test flies it."""
    if "rig" not in request.fixturenames:
        return
    rig: Rig = request.getfixturevalue("rig")
    latched = rig.latched_internal_error()
    if latched:
        log.warning("rebooting the ArduCopter fleet: %s", latched)
        rig.reboot()
