"""bench/scale.py end to end at a small size: two mapping agents in their own processes, driven by
the headless console over a router, MQTT on. Checks the bench works and measures what it says, not
how fast (the figures come from the bench itself, docs/operations.md)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_scale_bench_runs_mapping_agents_and_drives_them() -> None:
    spec = importlib.util.spec_from_file_location("bench_scale", ROOT / "bench" / "scale.py")
    assert spec is not None and spec.loader is not None
    scale = importlib.util.module_from_spec(spec)
    sys.modules["bench_scale"] = scale
    spec.loader.exec_module(scale)

    r = scale.run(2, 3.0, 1.0, True, 60.0, 720.0, True)
    assert r["robots"] == 2 and r["agents_crashed"] == 0 and r["bad_poses"] == 0
    assert r["lidar_rate_hz"] == 1.0 and r["lidar_samples_per_s"] == 720.0 and r["mqtt"]
    assert r["driving"] and r["robots_turning"] == 2 and r["teleops_sent"] > 0
    assert r["poses_received"] > 0 and r["delivered_by_sequence_ratio"] > 0.9
    assert 0 < r["agent_rss_max_bytes"] < 500 * 2**20 and r["agent_cpu_mean_ratio"] > 0
    table = scale.table(r)
    assert "2 robots" in table and "1 Hz x 720 samples" in table and "2 of 2 robots seen turning" in table
