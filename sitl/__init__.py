"""fleetgcs embedded simulator: N MAVLink 2 endpoints that behave like ArduCopter toward a ground station.

Python API: :class:`sitl.fleet.SimFleet` / :class:`sitl.fleet.FleetConfig`; CLI: ``sitl run``.
See docs/simulator.md. This package must not import ``gcs`` or ``agent``.
"""
