"""Incoming MAVLink: target filtering and routing by message type, the parameter protocol and
REQUEST_DATA_STREAM. Commands go to sitl/vehicle/commands.py, position targets to setpoints.py."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.vehicle.constants import (
    STREAM_GROUPS,
    param_name,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class Inbound:
    """Routes one decoded message from the GCS to the part of the vehicle that handles it."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v

    def handle(self, msg: mav.MAVLink_message, wall_now: float) -> None:
        """Process one decoded MAVLink message from the GCS."""
        v = self.v
        t = msg.get_type()
        if t == "HEARTBEAT":
            if msg.type == mav.MAV_TYPE_GCS:
                v.last_gcs_heartbeat = v.t
            return
        tgt_sys = getattr(msg, "target_system", None)
        if tgt_sys is not None and tgt_sys not in (0, v.sysid):
            return
        tgt_comp = getattr(msg, "target_component", None)
        if tgt_comp is not None and tgt_comp not in (0, 1):
            return
        if t == "COMMAND_LONG":
            v.command(msg, False)
        elif t == "COMMAND_INT":
            v.command(msg, True)
        elif t == "SET_POSITION_TARGET_GLOBAL_INT":
            v.setpoints.global_int(msg)
        elif t == "SET_POSITION_TARGET_LOCAL_NED":
            v.setpoints.local_ned(msg)
        elif t == "SET_MODE":
            v.set_mode(int(msg.custom_mode))
        elif t == "PARAM_REQUEST_LIST":
            for i, name in enumerate(v.params):
                self.send_param(name, i)
        elif t == "PARAM_REQUEST_READ":
            pname = v.params.name_at(msg.param_index) if msg.param_index >= 0 else param_name(msg.param_id)
            if pname is not None and pname in v.params:
                self.send_param(pname)
        elif t == "PARAM_SET":
            name = param_name(msg.param_id)
            if name in v.params and v.params.set(name, float(msg.param_value)):
                self.send_param(name)
        elif t == "REQUEST_DATA_STREAM":
            self.request_data_stream(msg)
        elif t == "MISSION_SET_CURRENT":
            v.set_mission_current(int(msg.seq))
        elif t.startswith("MISSION_"):
            v.mission.handle(msg, wall_now)

    def send_param(self, name: str, index: int | None = None) -> None:
        """PARAM_VALUE for ``name`` (its index unless the list being sent says otherwise)."""
        v = self.v
        v.send(
            mav.MAVLink_param_value_message(
                name.encode(),
                v.params[name],
                v.params.ptype(name),
                len(v.params),
                v.params.index(name) if index is None else index,
            )
        )

    def request_data_stream(self, msg: mav.MAVLink_message) -> None:
        """REQUEST_DATA_STREAM: set the interval of every message of the group (or all groups)."""
        v = self.v
        sid = msg.req_stream_id
        groups = list(STREAM_GROUPS) if sid == mav.MAV_DATA_STREAM_ALL else [sid]
        interval = 1.0 / msg.req_message_rate if (msg.start_stop and msg.req_message_rate > 0) else None
        for g in groups:
            for mid in STREAM_GROUPS.get(g, ()):
                (v.reply_link or v.link).set_message_interval(mid, interval)
