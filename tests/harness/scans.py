"""Scans for the loop closer's tests, prepared as the mapper prepares a node's scan."""

from __future__ import annotations

import numpy as np

from fleetlink.agent.mapping import scan as scanprep
from fleetlink.agent.mapping.closure import NodeScan
from fleetlink.agent.mapping.mapper import MapperConfig
from fleetlink.agent.mapping.matcher import scan_normals


def node_scan(ranges: np.ndarray, angles: np.ndarray, max_range: float | None = None) -> NodeScan:
    """A node's scan from ``ranges`` at ``angles`` (NaN or inf: no return), with the mapper's default
    range gate (``max_range`` instead of its maximum, if given), segments, normals and match points."""
    cfg = MapperConfig()
    r, a, hit = scanprep.prepare(ranges, angles, cfg.min_range, cfg.max_range if max_range is None else max_range)
    pts = scanprep.to_points(r[hit], a[hit])
    labels = scanprep.segment_labels(pts, cfg.segment_eps, cfg.segment_tau)
    keep = scanprep.filter_segments(labels, cfg.min_segment_points)
    kept = pts[keep]
    return NodeScan(r, a, hit, kept, scan_normals(pts, labels)[keep], scanprep.thin(kept, cfg.match_cell))
