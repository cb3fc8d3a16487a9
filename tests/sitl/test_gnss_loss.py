"""GNSS loss on one vehicle (issue 26): GPS_RAW_INT loses its fix, the estimate dead-reckons, and the
autopilot's own position failsafe takes over after the real autopilot's delay, with its words:
ArduCopter's EKF failsafe (EK3 position timeout 7 s + ekf_check 1 s, FS_EKF_ACTION 1 = LAND) and
PX4's mode fallback (EKF2_NOAID_TOUT 5 s, then Descend, shown as AUTO.LAND).
"""

from __future__ import annotations

from typing import Any

from sitl.dialect import mavlink as mav
from sitl.vehicle import GUIDED, SimVehicle
from sitl.vehicle.constants import GPS_FS_S
from tests.sitl.conftest import HOME, mavlink, offset
from tests.support.sitl_flight import ACCEPTED, DT, flying_vehicle, goto, reposition, saw, takeoff, wait_mode


class Recorder:
    """A vehicle link that keeps what the vehicle says."""

    def __init__(self) -> None:
        self.sent: list[mav.MAVLink_message] = []

    def send(self, msg: mav.MAVLink_message) -> None:
        self.sent.append(msg)

    def set_message_interval(self, msgid: int, interval_s: float | None) -> None:
        pass

    def texts(self) -> list[str]:
        return [m.text for m in self.sent if m.get_type() == "STATUSTEXT"]


def _run(v: SimVehicle, seconds: float) -> None:
    for _ in range(round(seconds / DT)):
        v.step(DT)


def _lost_on_a_leg(**params: float) -> tuple[SimVehicle, Recorder]:
    v = flying_vehicle()
    for name, value in params.items():
        v.params.set(name, value)
    rec = Recorder()
    v.link = rec
    goto(v, 300, 0)
    _run(v, 5.0)
    v.inject_gps_loss()
    return v, rec


def test_arducopter_ekf_failsafe_lands_after_eight_seconds_without_gps() -> None:
    v, rec = _lost_on_a_leg()
    raw = v.build(mav.MAVLINK_MSG_ID_GPS_RAW_INT)
    assert raw is not None and (raw.fix_type, raw.satellites_visible) == (0, 0)
    _run(v, GPS_FS_S - 0.5)
    assert v.state.mode == "GUIDED" and not v.ekf_failsafe, rec.texts()  # still dead-reckoning
    later = v.build(mav.MAVLINK_MSG_ID_GPS_RAW_INT)
    assert later is not None and (later.lat, later.lon) == (raw.lat, raw.lon)  # no longer updated
    _run(v, 1.0)
    assert v.state.mode == "LAND" and v.ekf_failsafe
    assert rec.texts()[-2:] == ["EKF variance", "EKF Failsafe: changed to LAND Mode"]
    # Without GPS a ground station cannot take it back into a position mode.
    assert not v.set_mode(GUIDED)
    _run(v, 40.0)
    assert v.state.landed and not v.state.armed and v.state.mode == "LAND"


def test_arducopter_ekf_failsafe_off_or_alt_hold_by_parameter() -> None:
    v, rec = _lost_on_a_leg(FS_EKF_THRESH=0.0)
    _run(v, GPS_FS_S + 2.0)
    assert v.state.mode == "GUIDED" and "EKF variance" not in rec.texts()
    v, rec = _lost_on_a_leg(FS_EKF_ACTION=2)
    _run(v, GPS_FS_S + 0.5)
    assert v.state.mode == "ALT_HOLD"
    assert rec.texts()[-1] == "EKF Failsafe: changed to ALT_HOLD Mode"


def test_px4_position_loss_descends_after_ekf2_noaid_timeout(px4: Any) -> None:
    fleet, g = px4(speedup=20.0)
    takeoff(g, 8.0)
    assert reposition(g, *offset(HOME[0], HOME[1], 200.0, 0.0), HOME[2] + 8.0, speed=5.0) == ACCEPTED
    g.wait("GLOBAL_POSITION_INT", lambda m: m.vx > 300, 10)
    vehicle = fleet.vehicle(0)
    lost = vehicle.state.sim_time
    vehicle.inject_gps_loss()
    g.wait("GPS_RAW_INT", lambda m: m.fix_type == 0 and m.satellites_visible == 0, 5)
    hb = wait_mode(g, (4, 6), timeout=5.0)  # Descend shows as AUTO.LAND
    assert hb.system_status == mavlink.MAV_STATE_CRITICAL
    after = vehicle.state.sim_time - lost
    assert 5.0 <= after < 6.5, after  # EKF2_NOAID_TOUT = 5 s
    saw(g, "Failsafe activated")
    g.heartbeat_msg(lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=30)
    assert vehicle.state.landed


def test_sim_gps1_enable_drops_the_gps_as_on_ardupilot_4_7_sitl() -> None:
    v = flying_vehicle()
    v.params.set("SIM_GPS1_ENABLE", 0)  # what a ground station sends to the real SITL
    _run(v, GPS_FS_S + 0.5)
    assert v.state.gps_fix == 0 and v.state.mode == "LAND"
    v.params.set("SIM_GPS1_ENABLE", 1)
    _run(v, 0.5)
    assert v.state.gps_fix == 3 and not v.ekf_failsafe and v.state.mode == "LAND"  # the mode stays
