"""Observation: fleet events, the live hub, metrics, the telemetry log and flight records."""
