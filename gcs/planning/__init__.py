"""Search planning: local frames, polygon analysis, camera spacing, coverage patterns, fleet division.

Submodules are imported explicitly (``from gcs.planning.geodesy import LocalFrame``); this package
initialiser stays import-free so that a planner importing one module does not pay for all of them.
"""
