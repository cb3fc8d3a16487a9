"""One rig per simulator per module: ``rig`` is parametrized over our simulator and real ArduCopter."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.ardupilot.binary import SKIP_REASON, ardupilot_binary
from tests.ardupilot.rig import Rig


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
