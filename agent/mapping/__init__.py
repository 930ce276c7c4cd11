"""Onboard mapping: scan preparation, scan matching, a log-odds occupancy grid, A* planning,
CARMEN log replay and the map codec. Everything here is pure (no I/O, time passed in) except
``share.py``, the Zenoh adapter. See docs/mapping.md.
"""

from fleetlink.agent.mapping.grid import GridConfig, LogOddsGrid
from fleetlink.agent.mapping.mapper import MapperConfig, OnboardMapper, ScanResult
from fleetlink.agent.mapping.planner import PathPlanner

__all__ = ["GridConfig", "LogOddsGrid", "MapperConfig", "OnboardMapper", "PathPlanner", "ScanResult"]
