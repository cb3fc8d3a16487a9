"""The one place that picks the MAVLink dialect: MAVLink 2, ardupilotmega (which includes common.xml).

``MAVLINK20`` is set before pymavlink is imported so any ``mavutil`` connection made in this process
(tests, tools) also speaks MAVLink 2.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = ["mavlink"]
