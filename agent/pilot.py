"""The pilot in control: a mode change the agent did not command hands the vehicle to a person.

A safety pilot flips the RC mode switch, or a supervisor's ground station sets a mode: the backend
sees the vehicle leave the mode the agent asked for (``Telemetry.pilot_mode``, from
:class:`agent.autopilot.flavours.base.ModeOwner`). Unless it is the vehicle's own failsafe (a
failsafe mode while the agent sees a cause: a battery, fence, GPS or link condition, or the
autopilot saying "failsafe"), the pilot has the vehicle from then on: the agent empties its queue,
sends nothing that moves the vehicle (its exception reactions only report), refuses every type-4
order and reports ``pilot`` (the mode) in its status. It gets the vehicle back when the pilot
puts it in the agent's mode again (ArduPilot GUIDED, PX4 Hold), or on an operator's release (a
type-4 ``resume`` from ``operator``), which it accepts only landed and disarmed or in one of the
flavour's release modes (a mode that holds position by itself: the pilot can take it back).
"""

from __future__ import annotations

from typing import Literal

from agent.autopilot.base import Autopilot, Telemetry

# Exception monitor conditions that explain a failsafe mode the vehicle entered by itself.
FAILSAFE_CAUSES = frozenset({"battery_low", "battery_critical", "fence_breach", "gps_lost"})
# Recent autopilot STATUSTEXTs (lower case) that name a failsafe. Not "ekf" alone: "EKF3 IMU0 is
# using GPS" comes with every flight and would make any foreign mode the vehicle's own.
FAILSAFE_WORDS = ("failsafe", "battery", "fence", "ekf variance", "gps glitch", "position estimate")

Change = Literal["took", "changed", "handed_back", "vehicle_failsafe"]


class PilotWatch:
    """Follows who flies the vehicle; :attr:`mode` is the pilot's mode while a pilot does."""

    def __init__(self, autopilot: Autopilot) -> None:
        self._autopilot = autopilot
        self.mode: str | None = None
        self._failsafe_mode: str | None = None  # a foreign mode already classed as the vehicle's own

    @property
    def active(self) -> bool:
        return self.mode is not None

    def update(self, t: Telemetry, conditions: set[str]) -> Change | None:
        """What changed since the last call, from the telemetry and the monitor's active conditions."""
        modes = self._autopilot.pilot_modes()
        if modes is None:
            return None
        failsafe_modes = modes[0]
        foreign = t.pilot_mode
        if self.mode is None:
            if foreign is None or foreign == self._failsafe_mode:
                self._failsafe_mode = foreign
                return None
            if foreign in failsafe_modes and _failsafe_cause(t, conditions):
                # The vehicle's own: the backend takes the mode as the agent's, so the agent's own
                # reaction and an operator's order still reach the vehicle.
                self._autopilot.adopt_mode()
                self._failsafe_mode = foreign
                return "vehicle_failsafe"
            self.mode = foreign
            return "took"
        if foreign is None:
            self.mode = None
            return "handed_back"
        if foreign != self.mode:
            self.mode = foreign
            return "changed"
        return None

    def release_refusal(self, t: Telemetry) -> str | None:
        """Why an operator's release is refused now, or None when it may be taken."""
        modes = self._autopilot.pilot_modes()
        if self.mode is None or modes is None:
            return None
        if t.landed and not t.armed:
            return None
        if self.mode in modes[1]:
            return None
        allowed = ", ".join(modes[1]) or "none"
        return (
            f"pilot in control in {self.mode}: a release is taken only landed and disarmed or in a mode "
            f"that holds position by itself ({allowed}); the pilot hands back by selecting the agent's mode"
        )

    def release(self) -> None:
        """The operator's release: the present mode is the agent's (nothing is sent to the vehicle)."""
        self._autopilot.adopt_mode()
        self.mode = None
        self._failsafe_mode = None


def _failsafe_cause(t: Telemetry, conditions: set[str]) -> bool:
    if conditions & FAILSAFE_CAUSES or t.autopilot_failsafe:
        return True
    return any(word in text.lower() for text in t.status_texts[-3:] for word in FAILSAFE_WORDS)


# What the vehicle flies in its own failsafe mode, in the agent's reaction words (StatusReport.failsafe).
MODE_REACTIONS = {"LAND": "land", "RTL": "rtl", "SMART_RTL": "rtl", "BRAKE": "hold", "LOITER": "hold"}
# Autopilot words that name a lost position estimate (ArduCopter "EKF variance"/"EKF Failsafe", PX4
# "No valid global position estimate") as the cause when the GPS fix itself still reads 3D. Not
# "EKF"/"GPS" alone: "EKF3 IMU0 is using GPS" and the yaw alignment texts come with every flight.
_GNSS_WORDS = ("ekf variance", "ekf failsafe", "position estimate", "gps glitch", "gps failsafe")


# What the autopilots say when their position failsafe fires (ArduCopter's ekf_check, PX4's commander).
POSITION_FAILSAFE_TEXTS = ("ekf variance", "ekf failsafe", "failsafe activated")


def landing_without_position(t: Telemetry, conditions: set[str]) -> bool:
    """The position failsafe fired while the vehicle was already landing on the agent's order (a
    daemon's or operator's land): no mode change shows it, the autopilot's words and the lost fix do."""
    if "gps_lost" not in conditions or t.mode != "LAND" or t.landed:
        return False
    if t.autopilot_failsafe:  # PX4: its heartbeat, as it sends no STATUSTEXT on the onboard link
        return True
    return any(w in text.lower() for text in t.status_texts[-3:] for w in POSITION_FAILSAFE_TEXTS)


def failsafe_name(t: Telemetry, conditions: set[str]) -> str:
    """Why the vehicle entered its own failsafe mode: ``gnss``, ``battery``, ``fence`` or ``vehicle``.

    The GNSS cause comes first: a vehicle without position lands whatever else is going on, and the
    daemon and the operator must know it cannot be sent anywhere.
    """
    texts = [text.lower() for text in t.status_texts[-3:]]
    if "gps_lost" in conditions or any(w in text for text in texts for w in _GNSS_WORDS):
        return "gnss"
    if conditions & {"battery_low", "battery_critical"} or any("battery" in text for text in texts):
        return "battery"
    if "fence_breach" in conditions or any("fence" in text for text in texts):
        return "fence"
    return "vehicle"
