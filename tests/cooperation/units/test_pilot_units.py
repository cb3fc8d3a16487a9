"""The pilot in control (issue 26) as pure units: who owns the vehicle's mode (agent side), the
pilot at the top of the vehicle authority (daemon side), and how ``pilot`` travels and shows."""

from __future__ import annotations

import json

from agent.autopilot.base import Telemetry
from agent.autopilot.flavours.ardupilot import ArduPilotFlavour
from agent.autopilot.flavours.base import ModeOwner
from agent.autopilot.flavours.px4 import Px4Flavour
from agent.autopilot.memory import MemoryAutopilot
from agent.pilot import PilotWatch
from gcs.commands.agents import _row
from gcs.http.models import AgentView
from protocol import status_binary
from protocol.actions import Land
from protocol.packets import StatusReport
from protocol.versions import render
from tests.support.authority import authority, status
from tests.support.pilot import ArduPilotModes


def _fly(
    owner: ModeOwner, flavour: ArduPilotFlavour | Px4Flavour, modes: list[str], armed: bool = True
) -> None:
    for mode in modes:
        owner.heartbeat(flavour, mode, armed)


def test_ardupilot_a_mode_the_agent_did_not_ask_for_is_the_pilots_until_guided() -> None:
    ap, owner = ArduPilotFlavour(), ModeOwner()
    owner.expect("GUIDED")
    _fly(owner, ap, ["STABILIZE", "GUIDED"], armed=False)  # on the ground: still the agent's
    assert owner.foreign is None
    _fly(owner, ap, ["GUIDED", "LOITER"])
    assert owner.foreign == "LOITER"
    _fly(owner, ap, ["LAND"])
    assert owner.foreign == "LAND"  # the pilot flies on, in another mode
    _fly(owner, ap, ["GUIDED"])
    assert owner.foreign is None  # the hand-back
    owner.expect("BRAKE")  # our hold
    _fly(owner, ap, ["BRAKE", "ALT_HOLD"])
    assert owner.foreign == "ALT_HOLD"
    _fly(owner, ap, ["GUIDED"])
    assert owner.foreign is None  # GUIDED hands back whatever the agent asked for last
    _fly(owner, ap, ["LOITER"])
    owner.adopt()  # the operator's release
    assert owner.foreign is None and owner.expected == "LOITER"


def test_px4_the_end_of_our_own_take_off_is_not_a_pilot_but_position_mode_is() -> None:
    px4, owner = Px4Flavour(), ModeOwner()
    owner.raw = "LOITER"
    owner.expect("TAKEOFF")
    _fly(owner, px4, ["TAKEOFF", "LOITER"])  # PX4 holds by itself after a take-off
    assert owner.foreign is None
    _fly(owner, px4, ["POSCTL"])
    assert owner.foreign == "POSCTL"
    _fly(owner, px4, ["LOITER"])  # Hold: the hand-back
    assert owner.foreign is None


def test_a_failsafe_mode_with_a_cause_is_the_vehicles_own_and_a_release_needs_a_holding_mode() -> None:
    ap = ArduPilotModes()
    watch = PilotWatch(ap)  # type: ignore[arg-type]
    flying = Telemetry(armed=True, landed=False, pilot_mode="RTL")
    assert watch.update(flying, {"battery_low"}) == "vehicle_failsafe"
    assert ap.adopted  # the backend lets the agent's reaction and the operator through again
    ap.adopted = False
    assert watch.update(flying, set()) is None and not watch.active
    assert watch.update(Telemetry(armed=True, landed=False, pilot_mode="ALT_HOLD"), set()) == "took"
    assert watch.release_refusal(Telemetry(armed=True, landed=False)) is not None  # by hand: refused
    assert watch.update(Telemetry(armed=True, landed=False, pilot_mode="LOITER"), set()) == "changed"
    assert watch.release_refusal(Telemetry(armed=True, landed=False)) is None
    watch.release()
    assert ap.adopted and not watch.active
    # An RTL nobody can explain is a pilot's (the safe side: the agent keeps its hands off).
    assert PilotWatch(ap).update(flying, set()) == "took"  # type: ignore[arg-type]
    assert PilotWatch(MemoryAutopilot()).update(flying, set()) is None  # a backend that does not track


def test_the_pilot_outranks_every_source_and_the_operators_resume_asks_for_the_drone_back() -> None:
    auth, link, decisions, _ = authority()
    auth.hold("d1", "collision", "conflict")
    auth.observe("d1", status(mode="LOITER", pilot="LOITER"))
    assert auth.pilot("d1") == "LOITER" and auth.control("d1").level == "pilot"
    sent = len(link.sent)
    assert not auth.replace("d1", "operator", "m", [Land(step=0)], "land", order="land")[0]
    assert not auth.hold("d1", "operator", "hold")[0]
    auth.reassert("d1")  # the periodic re-send of the collision pause: not while the pilot flies
    assert auth.release("d1", "collision", "clear") == (True, "pilot in control")
    assert len(link.sent) == sent  # nothing reached the drone
    ok, _ = auth.release("d1", "operator", "take it back")
    assert ok and link.modes()[-1] == "resume:operator"  # the agent decides
    auth.observe("d1", status(mode="LOITER"))
    assert auth.pilot("d1") is None
    assert [d[2] for d in decisions if d[1] == "pilot"] == ["pilot", "hand back"]
    assert auth.replace("d1", "operator", "m", [Land(step=0)], "land", order="land")[0]


def test_pilot_travels_in_v2_only_and_shows_in_gcs_agents() -> None:
    report = StatusReport(time=1.0, mode="LOITER", armed=True, landed=False, pilot="LOITER")
    assert json.loads(render(report, 2))["pilot"] == "LOITER"
    assert "pilot" not in json.loads(render(report, 1))
    assert status_binary.decode(status_binary.encode(report)).pilot == "LOITER"
    view = AgentView.model_validate(
        {
            "identity": "d1",
            "cid": 1,
            "connected": True,
            "lost": False,
            "peer": "127.0.0.1:1",
            "capabilities": {},
            "home": None,
            "status": report.model_dump(),
            "status_count": 1,
        }
    )
    assert _row(view).endswith("PILOT LOITER")


def test_two_requests_within_one_heartbeat_are_both_ours() -> None:
    """A return leg (GUIDED) then a collision hold (BRAKE) sent before the next heartbeat: the
    vehicle shows GUIDED, then BRAKE; neither is a pilot's (seen in CI: a BRAKE latched as the
    vehicle's own failsafe held a drone for the rest of an RTL-all)."""
    ap, owner = ArduPilotFlavour(), ModeOwner()
    owner.expect("BRAKE", now=0.0)
    _fly(owner, ap, ["GUIDED", "BRAKE"])  # the operator's hold, seen
    owner.expect("GUIDED", now=1.0)
    owner.expect("BRAKE", now=1.1)
    owner.heartbeat(ap, "GUIDED", True, now=1.5)
    owner.heartbeat(ap, "BRAKE", True, now=2.5)
    assert owner.foreign is None and owner.expected == "BRAKE"
    owner.heartbeat(ap, "LOITER", True, now=3.5)
    assert owner.foreign == "LOITER"  # the pilot's switch is still seen


def test_a_refused_or_stale_request_does_not_hide_a_pilots_switch_to_that_mode() -> None:
    ap, owner = ArduPilotFlavour(), ModeOwner()
    owner.expect("GUIDED", now=0.0)
    owner.heartbeat(ap, "STABILIZE", False, now=0.0)
    owner.heartbeat(ap, "GUIDED", True, now=0.5)
    owner.expect("LAND", now=1.0)
    owner.withdraw("LAND", "GUIDED")  # refused by the vehicle
    owner.heartbeat(ap, "LAND", True, now=2.0)
    assert owner.foreign == "LAND"
    owner.heartbeat(ap, "GUIDED", True, now=3.0)
    owner.expect("BRAKE", now=3.0)  # asked, never shown...
    owner.expect("GUIDED", now=3.2)
    owner.heartbeat(ap, "BRAKE", True, now=3.0 + 6.0)  # ...a switch to it much later is the pilot's
    assert owner.foreign == "BRAKE"


def test_a_boot_text_naming_the_ekf_is_no_failsafe_cause() -> None:
    ap = ArduPilotModes()
    watch = PilotWatch(ap)  # type: ignore[arg-type]
    flying = Telemetry(armed=True, landed=False, pilot_mode="BRAKE", status_texts=["EKF3 IMU0 is using GPS"])
    assert watch.update(flying, set()) == "took"
