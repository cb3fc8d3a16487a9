"""The simulated copter (ArduCopter behaviour; sitl/px4.py adds the PX4 personality), one module per job:

* ``core``: :class:`SimVehicle`, the vehicle state, the physics step and the Python API; it composes:
* ``inbound``: routing of incoming messages, the parameter protocol, REQUEST_DATA_STREAM;
* ``commands``: COMMAND_LONG/INT, one handler per MAV_CMD (``do_reposition``, ``nav_takeoff``, ...);
* ``setpoints``: SET_POSITION_TARGET_* (GUIDED targets);
* ``modes``: flight mode changes; ``arming``: pre-arm checks, arm, disarm;
* ``guidance``: what each mode flies (position control, take-off, RTL and landing profiles, limits);
* ``auto``: AUTO, flying the stored mission; ``fence``: the geofence; ``failsafes``: battery, EKF, GCS;
* ``telemetry``: every outgoing message, ``BUILDERS`` and the default streams;
* ``constants`` (mode numbers, tunables) and ``state`` (``VehicleState``, ``Failure``, ``LinkAPI``).
"""

from sitl.vehicle.constants import (
    ACRO,
    ALT_HOLD,
    ARMABLE_MODES,
    AUTO,
    BRAKE,
    FORCE_MAGIC,
    GUIDED,
    LAND,
    LOITER,
    MODE_NAMES,
    MODES,
    POSHOLD,
    POSITION_MODES,
    RTL,
    RTL_CLIMB,
    RTL_DESCEND,
    RTL_FINAL,
    RTL_LOITER,
    RTL_RETURN,
    SEV_CRITICAL,
    SEV_INFO,
    SEV_NOTICE,
    SEV_WARNING,
    STABILIZE,
    STREAM_GROUPS,
    param_name,
)
from sitl.vehicle.core import SimVehicle
from sitl.vehicle.state import Failure, LinkAPI, VehicleState
from sitl.vehicle.telemetry import BUILDERS, DEFAULT_STREAMS, Telemetry

__all__ = [
    "ACRO",
    "ALT_HOLD",
    "ARMABLE_MODES",
    "AUTO",
    "BRAKE",
    "BUILDERS",
    "DEFAULT_STREAMS",
    "FORCE_MAGIC",
    "GUIDED",
    "LAND",
    "LOITER",
    "MODES",
    "MODE_NAMES",
    "POSHOLD",
    "POSITION_MODES",
    "RTL",
    "RTL_CLIMB",
    "RTL_DESCEND",
    "RTL_FINAL",
    "RTL_LOITER",
    "RTL_RETURN",
    "SEV_CRITICAL",
    "SEV_INFO",
    "SEV_NOTICE",
    "SEV_WARNING",
    "STABILIZE",
    "STREAM_GROUPS",
    "Failure",
    "LinkAPI",
    "SimVehicle",
    "Telemetry",
    "VehicleState",
    "param_name",
]
