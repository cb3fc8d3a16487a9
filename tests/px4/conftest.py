"""One PX4 boot per agent backend for the whole package (``rig`` is package-scoped and parametrized over
the two backends): every flight of tests/px4 on one backend shares one fleet, and tests/conftest.py puts
each backend's tests in one xdist group, so with ``--dist loadgroup`` each backend boots PX4 once,
on one worker, in that backend's block of instance ids. Each boot is logged (logger ``tests.px4``, and a
line in ``$FLEETGCS_PX4_BOOT_LOG`` when set) so that this can be checked."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.px4.rig import BACKENDS, SPEED, PX4Rig, first_instance
from tests.px4.sih import SKIP_REASON, px4_dir

log = logging.getLogger("tests.px4")

EXTENDED_REASON = (
    "a real-PX4 flight run on request (FLEETGCS_PX4_TESTS=all): the synchronized mission, the survey, the "
    "lost link and the low battery add about 150 s per backend beyond the CI budget; the acceptance, "
    "pilot and GNSS flights gate CI: docs/testing.md 'PX4 SITL'"
)


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Before any fixture (no PX4 boot for a flight that is skipped)."""
    if item.get_closest_marker("px4_extended") and os.environ.get("FLEETGCS_PX4_TESTS") != "all":
        pytest.skip(EXTENDED_REASON)


def _log_boot(text: str) -> None:
    log.warning(text)
    path = os.environ.get("FLEETGCS_PX4_BOOT_LOG")
    if path:
        with Path(path).open("a") as f:
            f.write(f"{time.strftime('%H:%M:%S')} {text}\n")


@pytest.fixture(scope="package", params=BACKENDS)
def rig(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[PX4Rig]:
    backend = str(request.param)
    px4 = px4_dir()
    if px4 is None:
        pytest.skip(SKIP_REASON)
    if backend == "mavsdk":
        pytest.importorskip("mavsdk", reason="the MAVSDK backend needs the mavsdk package (extra [mavsdk])")
    first = first_instance(backend)
    if first is None:
        pytest.skip("PX4 instance ids 0-9 hold three blocks of three; FLEETGCS_PX4_BLOCK names none of them")
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    _log_boot(f"PX4 boot: backend {backend}, worker {worker}, instances {first}-{first + 2}, {SPEED:g}x")
    fleet = PX4Rig(px4, backend, tmp_path_factory.mktemp(f"px4-{backend}"), first).start()
    try:
        yield fleet
    finally:
        fleet.stop()
        wall = time.monotonic() - fleet.booted_at
        _log_boot(f"PX4 stop: backend {backend}, worker {worker}, {wall:.0f} s after its boot")


@pytest.fixture(autouse=True)
def leave_landed(request: pytest.FixtureRequest) -> Iterator[None]:
    """After each flight test (also a failed one): say where every vehicle is and how fast PX4's clock
    ran, then land whatever still flies and lift every hold, so that one failure does not cascade into
    the next flight of the same PX4 boot (bounded). Tests without ``rig`` need no PX4."""
    if "rig" not in request.fixturenames:
        yield
        return
    rig: PX4Rig = request.getfixturevalue("rig")
    rig.take_origins()
    started = {n: (time.monotonic(), rig.vehicle_now(n)) for n in rig.names}
    yield
    for name, agent in rig.agents.items():
        t = agent.autopilot.telemetry()
        wall, vehicle = started[name]
        rate = (rig.vehicle_now(name) - vehicle) / max(1e-3, time.monotonic() - wall)
        print(
            f"{name}: PX4 clock {rate:.2f}x over the test, mode {t.mode} armed {t.armed} landed {t.landed} "
            f"alt {t.alt_rel:.1f} battery {t.battery_pct} texts {[s for s in t.status_texts[-3:]]}"
        )
        # PX4 says why it refused or changed something on its GCS link only (none on the API link).
        print(f"{name}: PX4's texts {[s for _, s in rig.observers[name].texts_since(vehicle)][-8:]}")
        failsafes = [(round(at - vehicle, 1), flags) for at, flags in rig.failsafes[name] if at >= vehicle]
        if failsafes:  # PX4's own failsafes in this test, each with the conditions that held (PX4 s)
            print(f"{name}: PX4's failsafe conditions {failsafes}")
    active = rig.run(lambda: set(rig.d.missions.active))
    if active or not rig.all_landed():
        rig.call(rig.d.operator.bring_down("land", None, "test cleanup"))
        rig.wait(rig.all_landed, 150.0, "every vehicle landed after the test")
    rig.call(rig.d.operator.resume(None, "test cleanup"))
    # The daemon ends an operator's land/rtl order when it hears the vehicle landed, a status report
    # after the agent's own telemetry says so: the next flight's mission would be refused until then.
    rig.wait(
        lambda: all(rig.d.authority.order_owner(n) is None for n in rig.names),
        30.0,
        "the daemon to end every land/rtl order",
    )
