"""One PX4 rig per backend per module (``rig`` is parametrized over the agent's two backends)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.px4.rig import BACKENDS, PX4Rig
from tests.px4.sih import SKIP_REASON, px4_dir


@pytest.fixture(scope="module", params=BACKENDS)
def rig(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[PX4Rig]:
    backend = str(request.param)
    px4 = px4_dir()
    if px4 is None:
        pytest.skip(SKIP_REASON)
    if backend == "mavsdk":
        pytest.importorskip("mavsdk", reason="the MAVSDK backend needs the mavsdk package (extra [mavsdk])")
    fleet = PX4Rig(px4, backend, tmp_path_factory.mktemp(f"px4-{backend}")).start()
    try:
        yield fleet
    finally:
        fleet.stop()
