"""The pose graph back end (agent/mapping/posegraph.py): loops closed on synthetic trajectories
with a known truth, the robust kernel against a wrong closure, the Jacobians against numeric
derivatives, and bad input refused."""

from __future__ import annotations

import itertools
import math
import random

import numpy as np
import pytest

from fleetlink.agent.mapping.posegraph import PoseGraph, _errors, relative

INFO = np.diag([400.0, 400.0, 2500.0])  # 5 cm, 1.1 deg


def _square(side: float = 4.0, step: float = 0.5) -> list[tuple[float, float, float]]:
    """Truth: a square loop, counter-clockwise, back to the start, poses every ``step``."""
    out: list[tuple[float, float, float]] = []
    x = y = th = 0.0
    for _ in range(4):
        for _ in range(round(side / step)):
            out.append((x, y, th))
            x += step * math.cos(th)
            y += step * math.sin(th)
        th = math.remainder(th + math.pi / 2, 2 * math.pi)
    out.append((x, y, th))
    return out


def _drifted(truth: list[tuple[float, float, float]], yaw_bias: float, seed: int = 1) -> tuple[PoseGraph, list]:
    """Odometry edges with a heading bias and noise, chained into the initial guess (dead reckoning)."""
    rng = random.Random(seed)
    g = PoseGraph()
    odo = []
    for a, b in itertools.pairwise(truth):
        dx, dy, dth = relative(a, b)
        odo.append((dx + rng.gauss(0, 0.01), dy + rng.gauss(0, 0.01), dth + yaw_bias + rng.gauss(0, 0.005)))
    pose = truth[0]
    g.add_node(pose)
    for z in odo:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = (pose[0] + c * z[0] - s * z[1], pose[1] + s * z[0] + c * z[1], pose[2] + z[2])
        g.add_node(pose)
    for k, z in enumerate(odo):
        g.add_edge(k, k + 1, z, INFO)
    return g, odo


def _worst(g: PoseGraph, truth: list[tuple[float, float, float]]) -> float:
    return max(math.dist(p[:2], t[:2]) for p, t in zip(g.poses, truth, strict=True))


def test_a_loop_closure_pulls_a_drifted_square_back_onto_the_truth() -> None:
    truth = _square()
    g, _ = _drifted(truth, yaw_bias=0.02)
    drift = _worst(g, truth)
    assert drift > 1.0  # dead reckoning with a 1.1 deg/step heading bias ends far off
    # The last pose is where the first was: a closure says so (as a scan match would). Not robust:
    # 1.5 m off at the start is 30 sigma, which the kernel would take for a wrong match.
    g.add_edge(0, len(truth) - 1, relative(truth[0], truth[-1]), INFO * 4)
    solve = g.optimize()
    assert solve.converged
    assert solve.chi2_after < solve.chi2_before / 10
    assert _worst(g, truth) < 0.35 * drift
    assert math.dist(g.poses[-1][:2], truth[-1][:2]) < 0.1
    assert g.poses[0] == truth[0]  # the first node is held still
    assert solve.outliers == ()


def test_exact_measurements_keep_the_truth() -> None:
    truth = _square()
    g = PoseGraph()
    for p in truth:
        g.add_node(p)
    for k in range(len(truth) - 1):
        g.add_edge(k, k + 1, relative(truth[k], truth[k + 1]), INFO)
    g.add_edge(0, len(truth) - 1, relative(truth[0], truth[-1]), INFO)
    solve = g.optimize()
    assert solve.chi2_before < 1e-12 and solve.chi2_after < 1e-12
    assert _worst(g, truth) < 1e-9


def test_a_wrong_closure_is_an_outlier_under_the_kernel_and_bends_the_map_without_it() -> None:
    truth = _square()
    n = len(truth)
    # Odometry without bias (small noise); a false match says node 20 is 2 m from where it is.
    wrong = relative(truth[4], truth[20])
    wrong = (wrong[0] + 2.0, wrong[1], wrong[2])
    robust, _ = _drifted(truth, yaw_bias=0.0, seed=3)
    robust.add_edge(0, n - 1, relative(truth[0], truth[-1]), INFO, robust=True)
    bad = len(robust.edges)
    robust.add_edge(4, 20, wrong, INFO, robust=True)
    solve = robust.optimize(iterations=50)
    assert bad in solve.outliers
    assert _worst(robust, truth) < 0.3

    plain, _ = _drifted(truth, yaw_bias=0.0, seed=3)
    plain.add_edge(0, n - 1, relative(truth[0], truth[-1]), INFO)
    plain.add_edge(4, 20, wrong, INFO)
    plain.optimize(iterations=50)
    assert _worst(plain, truth) > 0.5  # believed, the false match drags the loop with it


def test_the_jacobians_match_numeric_derivatives() -> None:
    rng = random.Random(7)
    for _ in range(20):
        xi = (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3))
        xj = (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3))
        z = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1))
        e0, a, b = PoseGraph._error(xi, xj, z)
        h = 1e-6
        for k in range(3):
            d = [0.0, 0.0, 0.0]
            d[k] = h
            ei, _, _ = PoseGraph._error((xi[0] + d[0], xi[1] + d[1], xi[2] + d[2]), xj, z)
            ej, _, _ = PoseGraph._error(xi, (xj[0] + d[0], xj[1] + d[1], xj[2] + d[2]), z)
            np.testing.assert_allclose((ei - e0) / h, a[:, k], atol=1e-4)
            np.testing.assert_allclose((ej - e0) / h, b[:, k], atol=1e-4)
        # The vectorised form the solve uses gives the same error and Jacobians.
        ev, av, bv = _errors(np.array([xi]), np.array([xj]), np.array([z]))
        np.testing.assert_allclose(ev[0], e0, atol=1e-12)
        np.testing.assert_allclose(av[0], a, atol=1e-12)
        np.testing.assert_allclose(bv[0], b, atol=1e-12)


def test_another_fixed_node_holds_that_node_still() -> None:
    truth = _square()
    g, _ = _drifted(truth, yaw_bias=0.01)
    g.add_edge(0, len(truth) - 1, relative(truth[0], truth[-1]), INFO)
    held = g.poses[10]
    g.optimize(fixed=10)
    assert g.poses[10] == held


@pytest.mark.parametrize(
    ("call", "why"),
    [
        (lambda g: g.add_node((0.0, math.nan, 0.0)), "three finite numbers"),
        (lambda g: g.add_edge(0, 5, (1.0, 0.0, 0.0), INFO), "no such node"),
        (lambda g: g.add_edge(1, 1, (1.0, 0.0, 0.0), INFO), "cannot constrain itself"),
        (lambda g: g.add_edge(0, 1, (math.inf, 0.0, 0.0), INFO), "finite numbers"),
        (lambda g: g.add_edge(0, 1, (1.0, 0.0, 0.0), np.diag([1.0, -1.0, 1.0])), "positive definite"),
        (lambda g: g.add_edge(0, 1, (1.0, 0.0, 0.0), [[1.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "symmetric"),
        (lambda g: g.optimize(fixed=9), "no such node"),
        (lambda g: g.replace_edge(0, INFO), "no such edge"),
        (lambda g: g.remove_edges([0]), "no such edge"),
    ],
)
def test_bad_input_is_refused_with_the_reason(call: object, why: str) -> None:
    g = PoseGraph()
    g.add_node((0.0, 0.0, 0.0))
    g.add_node((1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=why):
        call(g)  # type: ignore[operator]
    assert len(g.poses) == 2 and g.edges == []  # nothing half-added


def test_edges_replaced_and_removed_solve_as_a_graph_built_without_them() -> None:
    """The solve reads the edges from arrays kept beside the list: after a replacement and a removal
    it must give, to the bit, what a graph built afresh with the edges left gives."""
    truth = _square()
    g, _ = _drifted(truth, yaw_bias=0.02)
    n = len(truth)
    wrong = (0.0, 0.0, 0.0)
    g.add_edge(0, n - 1, relative(truth[0], truth[-1]), INFO * 4)
    g.add_edge(3, n - 4, wrong, INFO, robust=True)  # a false closure, to be removed
    g.add_edge(5, n - 6, relative(truth[5], truth[-6]), INFO, robust=True)
    loose = np.diag([25.0, 25.0, 400.0])
    g.replace_edge(7, loose)  # a step held loosely (the final pass does this)
    g.remove_edges([n])  # the false closure: edges 0..n-2 are the steps, n-1 .. n+1 the closures
    with pytest.raises(ValueError, match="positive definite"):
        g.replace_edge(0, np.diag([1.0, 0.0, 1.0]))
    fresh = PoseGraph()
    for p in g.poses:
        fresh.add_node(p)
    for k, e in enumerate(g.edges):
        assert k != 7 or np.array_equal(e.info, loose)
        fresh.add_edge(e.i, e.j, e.z, e.info, robust=e.robust)
    assert len(g.edges) == n + 1 and not any(e.z == wrong for e in g.edges)
    assert np.array_equal(g.errors(), fresh.errors())
    a, b = g.optimize(), fresh.optimize()
    assert a.poses == b.poses and a.chi2_after == b.chi2_after
    assert _worst(g, truth) < 0.1


def test_position_priors_pull_a_graph_into_their_frame() -> None:
    """UWB fixes as priors: the graph starts in the robot's own frame (shifted and turned from the
    site's); priors at a few nodes, nothing held fixed, and every node lands on its site pose."""
    truth = _square()
    g, _ = _drifted(truth, yaw_bias=0.0)
    off = (2.0, -1.0, 0.4)  # the robot's frame seen from the site's
    c, s = math.cos(off[2]), math.sin(off[2])
    g.poses = [
        (c * (p[0] - off[0]) + s * (p[1] - off[1]), -s * (p[0] - off[0]) + c * (p[1] - off[1]), p[2] - off[2])
        for p in g.poses
    ]
    for k in range(0, len(truth), 4):
        g.add_prior(k, truth[k][:2], 0.05)
    assert _worst(g, truth) > 2.0
    g.optimize(fixed=None)
    assert _worst(g, truth) < 0.1
    assert max(abs(math.remainder(p[2] - t[2], 2 * math.pi)) for p, t in zip(g.poses, truth, strict=True)) < 0.05


def test_priors_are_refused_when_malformed() -> None:
    g = PoseGraph()
    g.add_node((0.0, 0.0, 0.0))
    for call in (
        lambda: g.add_prior(1, (0.0, 0.0), 0.1),
        lambda: g.add_prior(0, (math.nan, 0.0), 0.1),
        lambda: g.add_prior(0, (0.0,), 0.1),
        lambda: g.add_prior(0, (0.0, 0.0), 0.0),
    ):
        with pytest.raises(ValueError):
            call()
    assert g.priors == []
    g.add_prior(0, (1.0, 2.0), 0.1)
    g.add_prior(0, (3.0, 2.0), 0.1)
    g.optimize(fixed=None)
    assert g.poses[0][:2] == pytest.approx((2.0, 2.0))
