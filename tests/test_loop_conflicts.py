"""Online closures weighed against each other (``CloserConfig.conflict_chi2``), before the final pass
and online (``conflict_pair_chi2``).

A look-alike taken where the front end had drifted far holds a few nodes in the wrong place; the
true closures that come later are many, and the graph bends the front end's chain between the two, a
little each step, none past the solve's gate. Before the final pass, each group of closures holding a
large correction is taken out of a copy of the graph and the chi2 that lowers counted: the group
the rest does not bear out goes (MIT's Killian Court: 0.114 -> 0.041 m). Online, where no final pass
runs (a robot), the complete groups are weighed in pairs: two in conflict lower the chi2 by less
together than the two alone, summed, and the one worse per closure goes."""

from __future__ import annotations

import math
from dataclasses import fields

import numpy as np
import pytest

from fleetlink.agent.mapping.closure import CloserConfig, Closure, LoopCloser, NodeScan, compose, relative
from fleetlink.agent.mapping.grid import GridConfig

Pose = tuple[float, float, float]

EMPTY = NodeScan(
    np.zeros(0), np.zeros(0), np.zeros(0, dtype=bool), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2))
)
# The final pass's matches off: these graphs have no scans, only the online closures to weigh.
NO_MATCHES = {"final_per_node": 0, "final_any_heading": 0, "final_pair_per_node": 0}
FINAL_ONLY = {"conflict_pair_chi2": 0.0, **NO_MATCHES}  # the online weighing off


def _laps() -> list[Pose]:
    """Twice round a 12 x 6 m rectangle, a node every 0.3 m."""
    corners = [(0.0, 0.0), (12.0, 0.0), (12.0, 6.0), (0.0, 6.0)]
    out: list[Pose] = []
    for _ in range(2):
        for i in range(4):
            (x0, y0), (x1, y1) = corners[i], corners[(i + 1) % 4]
            th = math.atan2(y1 - y0, x1 - x0)
            n = round(math.hypot(x1 - x0, y1 - y0) / 0.3)
            out += [(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n, th) for k in range(n)]
    return out


TRUTH = _laps()
LAP = len(TRUTH) // 2


def _closer(config: CloserConfig, drift_deg: float = 0.1, nodes: int = len(TRUTH)) -> LoopCloser:
    """The laps as a front end would chain them (the first ``nodes``): every step turned ``drift_deg``
    too far."""
    closer = LoopCloser(config, GridConfig())
    _extend(closer, nodes, drift_deg)
    return closer


def _extend(closer: LoopCloser, nodes: int, drift_deg: float = 0.1) -> None:
    """Chain the laps on up to ``nodes`` (the same steps, to the bit, whether made at once or not)."""
    noise = np.random.default_rng(3).normal(0.0, 0.002, len(TRUTH) - 1)
    for k in range(len(closer), nodes):
        est = TRUTH[0]
        if k:  # from where the graph has the node before now, as a front end goes on after a solve
            z = relative(TRUTH[k - 1], TRUTH[k])
            est = compose(closer.poses[k - 1], (z[0], z[1], z[2] + math.radians(drift_deg) + noise[k - 1]))
        closer.add_node(float(k), est, EMPTY, information=np.diag([1e5, 1e5, 1e3]))


def _closures(nodes: range, along: float = 0.0) -> list[Closure]:
    """Second-lap nodes matched onto the first lap's submaps, ``along`` metres further on than they are."""
    out = []
    for k in nodes:
        a = k - LAP - (k - LAP) % 10  # the first node of the submap the node passes again
        z = relative(TRUTH[a], TRUTH[k])
        out.append(Closure(k, a, (z[0] + along, z[1], z[2]), 0.9, 0.9))
    return out


def _worst_revisit(closer: LoopCloser, nodes: range) -> float:
    """The worst error (m) of the second lap's ``nodes`` seen from where the first lap passed."""
    return max(
        math.dist(relative(closer.poses[k - LAP], closer.poses[k])[:2], relative(TRUTH[k - LAP], TRUTH[k])[:2])
        for k in nodes
    )


SPAN = range(LAP + 30, LAP + 67)  # the look-alike's nodes, the chain after them, the true closures'


def _look_alike_then_true(config: CloserConfig) -> LoopCloser:
    closer = _closer(config)
    closer.add_closures(_closures(range(LAP + 30, LAP + 33), along=3.0))  # three nodes, 3 m along
    closer.add_closures(_closures(range(LAP + 55, LAP + 67)))  # twelve, right, 22 nodes on
    return closer


def test_a_look_alike_group_the_true_closures_after_it_disagree_with_goes_before_the_final_pass() -> None:
    closer = _look_alike_then_true(CloserConfig(**FINAL_ONLY))
    # Both groups were large corrections and the online solve kept them all: the chain between bent.
    assert len(closer.closures) == 15 and closer.stats.dropped_by_solve == 0
    assert _worst_revisit(closer, SPAN) > 2.5
    closer.finish()
    assert closer.stats.conflicts_dropped == 3
    assert sorted(c.node for c in closer.closures) == list(range(LAP + 55, LAP + 67))
    assert _worst_revisit(closer, SPAN) < 0.2
    # The bookkeeping holds: each closure kept is still its own edge.
    for c, e in zip(closer.closures, closer._closure_edges, strict=True):
        edge = closer.graph.edges[e]
        assert (edge.i, edge.j, edge.z) == (c.anchor, c.node, c.z)


def test_without_the_check_the_look_alike_holds_its_nodes_off() -> None:
    closer = _look_alike_then_true(CloserConfig(conflict_drops=0, **FINAL_ONLY))
    closer.finish()
    assert closer.stats.conflicts_dropped == 0 and len(closer.closures) == 15
    assert _worst_revisit(closer, SPAN) > 2.5


def test_true_large_corrections_after_a_long_drift_are_kept() -> None:
    """A return after a whole lap drifting a degree every metre: a correction of metres the rest
    bears out (nothing else holds the chain), and twelve closures of it, not a conflict."""
    closer = _closer(CloserConfig(**NO_MATCHES), drift_deg=0.3)
    closer.add_closures(_closures(range(LAP + 30, LAP + 33)))
    closer.add_closures(_closures(range(LAP + 55, LAP + 67)))
    assert len(closer._large) >= 3  # large corrections, so weighed again
    assert closer.stats.conflicts_online == 0 and len(closer.closures) == 15  # weighed online: one return
    closer.finish()
    assert closer.stats.conflicts_dropped == 0 and len(closer.closures) == 15
    assert _worst_revisit(closer, SPAN) < 0.2


def test_online_the_look_alike_goes_once_the_true_closures_after_it_are_complete() -> None:
    """No final pass: the robot's own map. While the true group still grows (its last closure within
    ``conflict_gap_nodes`` of the newest node) nothing is weighed; once it is complete, the two are
    weighed as a pair and the look-alike goes."""
    closer = _closer(CloserConfig(**NO_MATCHES), nodes=LAP + 70)
    closer.add_closures(_closures(range(LAP + 30, LAP + 33), along=3.0))
    closer.add_closures(_closures(range(LAP + 55, LAP + 67)))
    assert closer.stats.conflicts_online == 0 and len(closer.closures) == 15
    _extend(closer, LAP + 90)
    closer.add_closures(_closures(range(LAP + 88, LAP + 90)))  # more closures, so a solve: weighed now
    assert closer.stats.conflicts_online == 3 and closer.stats.conflicts_dropped == 3
    assert sorted(c.node for c in closer.closures) == [*range(LAP + 55, LAP + 67), LAP + 88, LAP + 89]
    assert _worst_revisit(closer, SPAN) < 0.2
    for c, e in zip(closer.closures, closer._closure_edges, strict=True):
        edge = closer.graph.edges[e]
        assert (edge.i, edge.j, edge.z) == (c.anchor, c.node, c.z)


def test_online_the_look_alike_goes_with_all_the_nodes_there() -> None:
    closer = _look_alike_then_true(CloserConfig(**NO_MATCHES))
    assert closer.stats.conflicts_online == 3 and len(closer.closures) == 12
    assert _worst_revisit(closer, SPAN) < 0.2
    closer.finish()  # nothing more to let go
    assert closer.stats.conflicts_dropped == 3 and len(closer.closures) == 12


def test_online_two_true_returns_are_no_conflict_however_heavy() -> None:
    """Two true returns after a long drift, both heavy when weighed and the later one over the gate
    per closure: together they lower the chi2 by more than the two alone, summed (they hold each
    other up), not less, so neither goes."""
    closer = _closer(CloserConfig(**NO_MATCHES), drift_deg=0.4)
    closer.add_closures(_closures(range(LAP + 30, LAP + 40)))
    closer.add_closures(_closures(range(LAP + 80, LAP + 82)))
    assert closer.stats.conflicts_online == 0 and len(closer.closures) == 12  # weighed, kept
    cfg = closer.config
    base = closer._chi2_without()
    a, b = base - closer._chi2_without(range(10)), base - closer._chi2_without(range(10, 12))
    assert min(a, b) > cfg.conflict_chi2 and b / 2 > cfg.conflict_chi2_per_closure  # either could go alone
    assert a + b < base - closer._chi2_without(range(12))


def test_online_a_group_a_waiting_correction_could_still_join_is_not_weighed() -> None:
    """A large correction waiting for its confirmation near a group could still join it: the group
    is not complete, and not weighed, until it has gone."""
    closer = _closer(CloserConfig(**NO_MATCHES), nodes=LAP + 100)
    closer.add_closures(_closures(range(LAP + 30, LAP + 33), along=3.0))
    waiting = _closures(range(LAP + 75, LAP + 76))[0]
    closer._pending.append(waiting)  # as ``_classify`` holds a fresh large correction
    closer.add_closures(_closures(range(LAP + 55, LAP + 67)))
    assert closer.stats.conflicts_online == 0 and len(closer.closures) == 15
    closer._pending.remove(waiting)  # expired unconfirmed
    closer.add_closures(_closures(range(LAP + 98, LAP + 100)))
    assert closer.stats.conflicts_online == 3 and len(closer.closures) == 14


def test_online_the_weighing_counts_against_the_pace_of_solves() -> None:
    """On a robot the graph is solved at most once per ``len / solve_nodes_per_s`` seconds; a weighing
    solves copies of it several times, and the next solve waits for each of those too."""
    closer = _closer(CloserConfig(**NO_MATCHES))
    closer._add(_closures(range(LAP + 30, LAP + 33), along=3.0))
    closer._solve_online(wait=2.0)
    assert closer._solved_t == closer.times[-1]  # one group: nothing weighed
    closer._add(_closures(range(LAP + 55, LAP + 67)))
    closer._solve_online(wait=2.0)
    assert closer.stats.conflicts_online == 3
    # The base, the two groups, their pair, and the solve after the look-alike went.
    assert closer._solved_t == closer.times[-1] + 2.0 * 5


def test_online_only_the_newest_complete_groups_are_weighed() -> None:
    """A weighing's cost grows with the groups it weighs: only the newest ``conflict_online_groups``.
    The true group and a later one complete at once: with two, the look-alike is left out."""
    stats = []
    for newest in (2, 3):
        closer = _closer(CloserConfig(conflict_online_groups=newest, **NO_MATCHES), nodes=LAP + 110)
        closer.add_closures(_closures(range(LAP + 30, LAP + 33), along=3.0))
        # Two true groups found at once, both large corrections of the drifted chain, both complete.
        closer._add(_closures(range(LAP + 55, LAP + 60)) + _closures(range(LAP + 80, LAP + 85)))
        closer._solve_online()
        stats.append((closer.stats.conflicts_online, len(closer.closures), len(closer._suspects())))
    assert stats == [(0, 13, 3), (3, 10, 2)]  # (let go, closures kept, groups of large corrections)


def test_the_same_graph_weighs_the_same_way() -> None:
    a, b = (_look_alike_then_true(CloserConfig(**FINAL_ONLY)) for _ in range(2))
    a.finish()
    b.finish()
    assert a.poses == b.poses and a.closures == b.closures
    c, d = (_look_alike_then_true(CloserConfig(**NO_MATCHES)) for _ in range(2))
    assert c.poses == d.poses and c.closures == d.closures


@pytest.mark.parametrize("name", [f.name for f in fields(CloserConfig) if f.name.startswith("conflict_")])
def test_a_conflict_setting_out_of_range_is_refused_with_its_name(name: str) -> None:
    with pytest.raises(ValueError, match=name):
        CloserConfig(**{name: -1})
    with pytest.raises(ValueError, match=name):
        CloserConfig(**{name: math.nan})
