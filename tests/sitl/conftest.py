"""Fixtures for the simulator tests: real fleets on ephemeral loopback ports and a small pymavlink GCS.

Every wait is bounded both in wall time and in iterations, so a misbehaving simulator fails a test
instead of hanging the suite.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from sitl.fleet import FleetConfig, SimFleet

mavlink = mavutil.mavlink
SPEEDUP = 25.0
HOME = (47.397742, 8.545594, 488.0)

MODE = {"STABILIZE": 0, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9, "BRAKE": 17}


class Gcs:
    """A minimal ground station over pymavlink, talking to one simulated vehicle."""

    def __init__(self, url: str, sysid: int = 1) -> None:
        self.url = url
        self.sysid = sysid
        self.m = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.texts: list[str] = []
        if url.startswith("udp"):
            self.heartbeat()

    def close(self) -> None:
        self.m.close()

    def heartbeat(self) -> None:
        self.m.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def recv(self, timeout: float) -> Any:
        """One message or None; STATUSTEXTs are remembered in ``texts``."""
        msg = self.m.recv_match(blocking=True, timeout=timeout)
        if msg is not None and msg.get_type() == "STATUSTEXT":
            self.texts.append(msg.text)
        return msg

    def wait(
        self,
        types: str | tuple[str, ...],
        cond: Callable[[Any], bool] | None = None,
        timeout: float = 5.0,
    ) -> Any:
        """First message of ``types`` satisfying ``cond`` within ``timeout`` wall seconds, else fail."""
        if isinstance(types, str):
            types = (types,)
        deadline = time.monotonic() + timeout
        for _ in range(200_000):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            msg = self.recv(min(0.2, left))
            if msg is None or msg.get_type() not in types:
                continue
            if msg.get_srcSystem() != self.sysid:
                continue
            if cond is None or cond(msg):
                return msg
        raise AssertionError(f"no {types} matching condition within {timeout} s")

    def drain(self, seconds: float) -> list[Any]:
        """Everything received during ``seconds`` of wall time."""
        out = []
        deadline = time.monotonic() + seconds
        for _ in range(200_000):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            msg = self.recv(min(0.05, left))
            if msg is not None:
                out.append(msg)
        return out

    def command(self, cmd: int, *params: float, comp: int = 1, timeout: float = 3.0) -> int:
        """COMMAND_LONG and its COMMAND_ACK result."""
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.m.mav.command_long_send(self.sysid, comp, cmd, 0, *p)
        ack = self.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout)
        return int(ack.result)

    def command_int(
        self, cmd: int, frame: int, p1: float, p2: float, x: int, y: int, z: float, timeout: float = 3.0
    ) -> int:
        """COMMAND_INT and its COMMAND_ACK result."""
        self.m.mav.command_int_send(self.sysid, 1, frame, cmd, 0, 0, p1, p2, 0, 0, x, y, z)
        ack = self.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout)
        return int(ack.result)

    def set_mode(self, name: str) -> int:
        flag = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, flag, MODE[name])

    def stream(self, msgid: int, hz: float) -> None:
        result = self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msgid, 1e6 / hz)
        assert result == mavlink.MAV_RESULT_ACCEPTED

    def arm(self, timeout: float = 10.0) -> None:
        """Retry arming until accepted (pre-arm settles in sim time)."""
        deadline = time.monotonic() + timeout
        for _ in range(1000):
            if self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED:
                return
            if time.monotonic() > deadline:
                break
            time.sleep(0.05)
        raise AssertionError(f"could not arm; texts {self.texts[-3:]}")

    def takeoff(self, alt: float, timeout: float = 10.0) -> Any:
        """GUIDED, arm, takeoff to ``alt`` and wait until the reported altitude is within 0.5 m."""
        self.stream(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10)
        assert self.set_mode("GUIDED") == mavlink.MAV_RESULT_ACCEPTED
        self.arm()
        assert self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt) == mavlink.MAV_RESULT_ACCEPTED
        return self.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > (alt - 0.5) * 1000, timeout)

    def goto(self, lat: float, lon: float, alt_rel: float, mask: int = 0x0DF8, frame: int = 6) -> None:
        self.m.mav.set_position_target_global_int_send(
            0, self.sysid, 1, frame, mask, round(lat * 1e7), round(lon * 1e7), alt_rel, 0, 0, 0, 0, 0, 0, 0, 0
        )

    def heartbeat_msg(self, cond: Callable[[Any], bool] | None = None, timeout: float = 5.0) -> Any:
        return self.wait("HEARTBEAT", cond, timeout)


def offset(lat: float, lon: float, north: float, east: float) -> tuple[float, float]:
    """Flat-earth offset (same scaling as the simulator)."""
    return lat + north / 111318.84502145034, lon + east / (111318.84502145034 * math.cos(math.radians(lat)))


def dist_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    dn = (lat2 - lat1) * 111318.84502145034
    de = (lon2 - lon1) * 111318.84502145034 * math.cos(math.radians(lat1))
    return math.hypot(dn, de)


@pytest.fixture
def make_fleet() -> Iterator[Callable[..., SimFleet]]:
    """Factory: ``make_fleet(vehicles=2, speedup=..., ...)`` returns a started fleet, stopped afterwards."""
    fleets: list[SimFleet] = []

    def factory(**kw: Any) -> SimFleet:
        kw.setdefault("base_port", 0)
        kw.setdefault("speedup", SPEEDUP)
        kw.setdefault("home", HOME)
        kw.setdefault("seed", 1)
        kw.setdefault("prearm_delay_s", 2.0)
        fleet = SimFleet(FleetConfig(**kw))
        fleets.append(fleet)
        return fleet.start()

    yield factory
    for f in fleets:
        f.stop()


@pytest.fixture
def make_gcs() -> Iterator[Callable[..., Gcs]]:
    clients: list[Gcs] = []

    def factory(url: str, sysid: int = 1) -> Gcs:
        g = Gcs(url, sysid)
        clients.append(g)
        return g

    yield factory
    for g in clients:
        g.close()


@pytest.fixture
def px4(
    make_fleet: Callable[..., SimFleet], make_gcs: Callable[..., Gcs]
) -> Callable[..., tuple[SimFleet, Gcs]]:
    """``px4(**config)``: a one-vehicle PX4 fleet (udpout on an ephemeral port) and a GCS on it."""

    def start(**kw: Any) -> tuple[SimFleet, Gcs]:
        fleet = make_fleet(flavour="px4", **kw)
        g = make_gcs(fleet.endpoints[0])
        g.heartbeat_msg()
        return fleet, g

    return start
