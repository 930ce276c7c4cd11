"""The final pass's walls seen from behind (agent/mapping/closure.py, ``final_min_facing_share``): a
wall 0.3 m thick, a room above it and a corridor below. A scan from the corridor sees the wall's lower
face; matched onto what the room saw, from a guess a few centimetres off, the refinement pulls that
face onto the upper one, 0.3 m across, every inlier on a surface that faces away from the scan. So
three final-pass edges (each 0.33-0.36 m off the reference's relation) laid intel's corrected log's
scan 814 on such a face, its step 0.19 m across where the raw log's own odometry drives straight."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fleetlink.agent.mapping.closure import Check, CloserConfig, LoopCloser, NodeScan, compose, run_check
from fleetlink.agent.mapping.grid import GridConfig
from fleetlink.field.raycast import Raycaster
from fleetlink.shared.se2 import Pose
from tests.harness.scans import node_scan


def _box(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]]


WALLS = np.array(
    _box(-3.0, -2.5, 3.0, 2.5)  # a 6 x 5 m space
    + _box(-3.0, -0.15, 0.5, 0.15)  # across it, a wall 0.3 m thick with a door in it (x 0.5-1.4)
    + _box(1.4, -0.15, 3.0, 0.15)
    + _box(-2.2, 1.6, -1.9, 1.9)  # a post in the room above
    + _box(2.0, -2.0, 2.3, -1.8)  # and one in the corridor below
)
WELL_POSED = np.diag([1.0e5, 1.0e5, 1.0e3])


def _scan(x: float, y: float, heading: float = 0.0, fov: float = 2.0 * math.pi, beams: int = 720) -> NodeScan:
    """What a lidar at (x, y) facing ``heading`` sees over ``fov``, prepared as the mapper prepares it."""
    full = fov >= 2.0 * math.pi
    step = fov / beams if full else fov / (beams - 1)
    angles = -fov / 2.0 + step * np.arange(beams)
    return node_scan(Raycaster(WALLS).cast_fan(x, y, heading - fov / 2.0, step, beams, 12.0), angles)


# The submap: three scans from the room above, in the frame of the first (at (-1, 1), facing +x).
ROOM_VIEWS = ((-1.0, 1.0), (-2.5, 0.8), (0.2, 1.2))


def _final_check(scan: NodeScan, guess: Pose, config: CloserConfig, final: bool = True) -> Check:
    """``scan`` against the room's submap from ``guess`` (the sensor in the submap's frame), as the
    final pass checks a node (``final``: or as an online check)."""
    parts = tuple(((x + 1.0, y - 1.0, 0.0), _scan(x, y)) for x, y in ROOM_VIEWS)
    window = (config.final_window_xy, config.final_window_theta)
    return Check(
        1, 0, 0, scan, guess, window, None, parts, config, GridConfig(), (0.0, 0.0, 0.0), partial=True, unique=True,
        final=final,
    )  # fmt: skip


@pytest.mark.parametrize("below", [-0.5, -1.0])
def test_a_final_match_onto_a_walls_far_face_is_refused(below: float) -> None:
    """A 180-degree scan from the corridor at (-1, ``below``), facing the wall, the graph's guess 0.2 m
    too near the wall: without the gate the final pass takes it 0.3 m off, the lower face on the upper
    (a partial match: the wall says nothing along itself); with it, refused. An online check of a small
    correction is exempt (``min_facing_share`` asks only large ones), as before."""
    scan = _scan(-1.0, below, math.pi / 2, math.pi, 181)
    truth_y = below - 1.0  # in the submap's frame
    guess = (0.0, truth_y + 0.2, math.pi / 2)
    taken = run_check(_final_check(scan, guess, CloserConfig(final_min_facing_share=0.0)))
    assert taken.closure is not None, taken.outcome
    assert abs(taken.closure.z[1] - (truth_y + 0.3)) < 0.03, taken.closure.z  # on the far face
    refused = run_check(_final_check(scan, guess, CloserConfig()))
    assert refused.closure is None and refused.outcome == "far side"
    online = run_check(_final_check(scan, guess, CloserConfig(), final=False))
    assert online.closure is not None, online.outcome


def test_a_final_match_on_the_side_it_was_mapped_from_is_kept() -> None:
    """The same wall seen from the room, the guess 0.2 m off: the final pass keeps the match, and it
    puts the scan where it was taken."""
    scan = _scan(-1.5, 0.7, -math.pi / 2, math.pi, 181)
    truth = (-0.5, -0.3, -math.pi / 2)
    res = run_check(_final_check(scan, (truth[0], truth[1] - 0.2, truth[2]), CloserConfig()))
    assert res.closure is not None, res.outcome
    assert abs(res.closure.z[1] - truth[1]) < 0.03, res.closure.z


def _pairs(first: tuple[float, float], second: tuple[float, float], off: float, config: CloserConfig) -> LoopCloser:
    """A closer with two nodes (360-degree scans), the second put ``off`` m further along y than it was
    taken, for its final pass's scan pairs (``_scan_pairs``)."""
    closer = LoopCloser(config, GridConfig())
    closer.add_node(0.0, (first[0], first[1], 0.0), _scan(*first), information=WELL_POSED)
    closer.add_node(1.0, (second[0], second[1] + off, 0.0), _scan(*second), information=WELL_POSED)
    return closer


def test_a_scan_pair_across_a_thick_wall_is_no_edge() -> None:
    """The room's scan at (-1, 1) and the corridor's at (-1, -1): the pair's refinement lays the lower
    face on the upper one whatever the guess, 0.3 m short of the 2 m between them. Without the gate it
    is an edge; with it, none, and counted."""
    cfg = CloserConfig(submap_nodes=50, min_gap_nodes=50)
    for off in (0.0, 0.2):
        plain = _pairs(
            (-1.0, 1.0), (-1.0, -1.0), off, CloserConfig(submap_nodes=50, min_gap_nodes=50, final_min_facing_share=0.0)
        )
        (edge,) = plain._scan_pairs(np.array(plain.poses))
        assert abs(edge.z[1] + 1.7) < 0.03, edge.z
        gated = _pairs((-1.0, 1.0), (-1.0, -1.0), off, cfg)
        assert gated._scan_pairs(np.array(gated.poses)) == []
        assert gated.stats.final_behind == 1


def test_a_scan_pair_on_one_side_of_the_wall_is_an_edge() -> None:
    """Two scans in the room 1 m apart, the second put 0.1 m off: the pair is an edge and measures them
    1 m apart."""
    closer = _pairs((-1.5, 1.0), (-0.5, 1.0), 0.1, CloserConfig(submap_nodes=50, min_gap_nodes=50))
    (edge,) = closer._scan_pairs(np.array(closer.poses))
    assert abs(edge.z[0] - 1.0) < 0.02 and abs(edge.z[1]) < 0.02, edge.z
    assert closer.stats.final_behind == 0


@pytest.mark.parametrize("share", [-0.1, 1.1, math.nan])
def test_the_final_facing_share_is_a_share(share: float) -> None:
    with pytest.raises(ValueError, match="final_min_facing_share"):
        CloserConfig(final_min_facing_share=share)


def test_the_final_pass_refuses_a_node_laid_on_the_far_face() -> None:
    """Through ``_verify_all`` (what ``finish`` runs per submap): ten nodes in the room above make a
    submap; a node in the corridor below, the graph putting it 0.2 m too near the wall, is matched
    against it as the final pass matches it. Refused with the gate (counted apart from the online
    gate's refusals); without it, an edge 0.3 m off."""
    views = [(-2.5 + 0.5 * i, 1.0 + 0.1 * (i % 3)) for i in range(10)]
    below = (-1.0, -0.5)
    for share in (0.6, 0.0):
        cfg = CloserConfig(submap_nodes=10, min_gap_nodes=50, final_min_facing_share=share)
        closer = LoopCloser(cfg, GridConfig())
        for k, (x, y) in enumerate(views):
            closer.add_node(float(k), (x, y, 0.0), _scan(x, y), information=WELL_POSED)
        scan = _scan(below[0], below[1], math.pi / 2, math.pi, 181)
        closer.add_node(10.0, (below[0], below[1] + 0.2, math.pi / 2), scan, information=WELL_POSED)
        window = (cfg.final_window_xy, cfg.final_window_theta)
        found = closer._verify_all([10], closer.submaps[0], window, partial=True)
        if share > 0:
            assert found == [] and closer.stats.final_behind == 1 and closer.stats.rejected_behind == 0
        else:
            (edge,) = found
            at = compose(closer.poses[0], edge.z)
            assert abs(at[1] - (below[1] + 0.3)) < 0.03, at  # on the room's face of the wall
