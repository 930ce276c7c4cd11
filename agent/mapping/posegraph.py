"""A 2D pose graph and its least-squares solve: the back end that closes loops (issue 17).

Nodes are poses ``(x, y, theta)`` in one frame (the mapper's keyframes). Edges are measured
relative poses between two nodes, each with a 3x3 information matrix (the inverse covariance of
``dx dy dtheta`` in the first node's frame): odometry or scan matching between consecutive
keyframes, and loop closures between a keyframe and an older one it was matched against.

    g = PoseGraph()
    a = g.add_node((0.0, 0.0, 0.0)); b = g.add_node((1.0, 0.0, 0.0))
    g.add_edge(a, b, (1.0, 0.0, 0.0), np.diag([100.0, 100.0, 400.0]))
    result = g.optimize()            # Gauss-Newton; the first node (or ``fixed``) held still

The error of an edge ``i -> j`` with measurement ``z`` is ``t2v(Z^-1 (X_i^-1 X_j))`` and the solve
minimises the sum of ``rho(e^T Omega e)`` over the edges, with ``rho`` the identity (odometry) or
the Cauchy kernel for edges marked ``robust`` (closures: a wrong match is down-weighted instead of
bending the whole map). Jacobians and the update follow Grisetti, Kümmerle, Stachniss and
Burgard, "A tutorial on graph-based SLAM" (IEEE ITS Magazine, 2010), section IV. The normal
equations are assembled over all edges at once (numpy) and solved sparse (scipy's SuperLU): a
thousand nodes with a few hundred closures solve in about 20 ms per iteration.

Bad input (a non-finite pose or measurement, an information matrix that is not symmetric positive
definite, an edge to an unknown node or to itself) raises ``ValueError`` saying which. Position
priors (``add_prior``: a UWB fix of a node) anchor a graph in the site frame. numpy and scipy;
no clock, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fleetlink.shared.se2 import Pose, relative, wrap

__all__ = ["Edge", "PoseGraph", "Prior", "Solve", "relative"]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Edge:
    i: int
    j: int
    z: Pose
    """Pose of node ``j`` in the frame of node ``i``, as measured."""
    info: F64
    """3x3 information matrix of ``z`` (dx, dy in metres, dtheta in radians)."""
    robust: bool = False
    """A loop closure: Cauchy-weighted, so one wrong match does not bend the map. The weight is
    judged at the current guess, so a true closure many sigma off it (drift far beyond what the
    odometry's information admits) is down-weighted too: add such a closure as a plain edge once
    the front end has checked it."""


@dataclass(frozen=True, slots=True)
class Solve:
    poses: list[Pose]
    iterations: int
    chi2_before: float
    chi2_after: float
    """Sum of e^T Omega e over every edge (no kernel), before and after."""
    converged: bool
    outliers: tuple[int, ...] = ()
    """Indices (into ``edges``) of robust edges whose final weight fell below one half: closures
    the solve did not believe."""


@dataclass(frozen=True, slots=True)
class Prior:
    """A measured position of one node in the graph's frame (a UWB fix): error ``x_i - z``."""

    i: int
    xy: tuple[float, float]
    sigma: float
    """Standard deviation of each coordinate, metres."""


class PoseGraph:
    def __init__(self, cauchy_c: float = 1.0) -> None:
        if not (math.isfinite(cauchy_c) and cauchy_c > 0):
            raise ValueError(f"cauchy_c must be a finite number > 0, got {cauchy_c!r}")
        self.cauchy_c = cauchy_c
        self.poses: list[Pose] = []
        self._edges: list[Edge] = []
        self.priors: list[Prior] = []
        # The edges as arrays, kept beside the list (a row written per edge added): a solve and
        # ``errors`` read them whole, and packing 10 000+ edges again each time cost more than the
        # solve on long replays. Capacity doubles; only the first len(edges) rows mean anything.
        self._ii = np.zeros(0, dtype=np.int64)
        self._jj = np.zeros(0, dtype=np.int64)
        self._zz = np.zeros((0, 3))
        self._om = np.zeros((0, 3, 3))
        self._robust = np.zeros(0, dtype=bool)

    @property
    def edges(self) -> Sequence[Edge]:
        """The edges, in the order added (change them with ``add_edge``, ``replace_edge`` and
        ``remove_edges``, which keep the solve's arrays in step)."""
        return self._edges

    def edge_arrays(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64]:
        """Each edge's two nodes (``i``, ``j``) and measurement ``z`` as arrays, in the order added
        (views: not to be written)."""
        m = len(self._edges)
        return self._ii[:m], self._jj[:m], self._zz[:m]

    def _packed(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F64, F64, npt.NDArray[np.bool_]]:
        m = len(self._edges)
        return self._ii[:m], self._jj[:m], self._zz[:m], self._om[:m], self._robust[:m]

    def _write(self, k: int, e: Edge) -> None:
        if k >= len(self._ii):
            cap = max(64, 2 * len(self._ii))
            self._ii = np.resize(self._ii, cap)
            self._jj = np.resize(self._jj, cap)
            self._zz = np.resize(self._zz, (cap, 3))
            self._om = np.resize(self._om, (cap, 3, 3))
            self._robust = np.resize(self._robust, cap)
        self._ii[k], self._jj[k], self._zz[k], self._om[k], self._robust[k] = e.i, e.j, e.z, e.info, e.robust

    def add_prior(self, i: int, xy: Sequence[float], sigma: float) -> Prior:
        """Node ``i`` measured at ``xy`` (each coordinate with sd ``sigma``) in the graph's frame: what
        anchors the graph to the site (a UWB fix). With priors no node is held fixed."""
        if not 0 <= i < len(self.poses):
            raise ValueError(f"prior on node {i}: no such node (the graph has {len(self.poses)})")
        if len(xy) != 2 or not all(math.isfinite(float(v)) for v in xy):
            raise ValueError(f"prior on node {i}: position must be two finite numbers, got {tuple(xy)!r}")
        if not (math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"prior on node {i}: sigma must be a finite number > 0, got {sigma!r}")
        p = Prior(i, (float(xy[0]), float(xy[1])), float(sigma))
        self.priors.append(p)
        return p

    def add_node(self, pose: Sequence[float]) -> int:
        """A node at ``pose`` (the initial guess); its index."""
        if len(pose) != 3 or not all(math.isfinite(float(v)) for v in pose):
            raise ValueError(f"node pose must be three finite numbers (x, y, theta), got {tuple(pose)!r}")
        self.poses.append((float(pose[0]), float(pose[1]), wrap(float(pose[2]))))
        return len(self.poses) - 1

    def add_edge(self, i: int, j: int, z: Sequence[float], info: npt.ArrayLike, *, robust: bool = False) -> Edge:
        """A measured pose of ``j`` in ``i``'s frame with its information matrix."""
        n = len(self.poses)
        if not (0 <= i < n and 0 <= j < n):
            raise ValueError(f"edge {i}->{j}: no such node (the graph has {n})")
        if i == j:
            raise ValueError(f"edge {i}->{j}: a node cannot constrain itself")
        if len(z) != 3 or not all(math.isfinite(float(v)) for v in z):
            raise ValueError(f"edge {i}->{j}: measurement must be three finite numbers, got {tuple(z)!r}")
        om = _information(info, i, j)
        e = Edge(i, j, (float(z[0]), float(z[1]), wrap(float(z[2]))), om, robust)
        self._write(len(self._edges), e)
        self._edges.append(e)
        return e

    def replace_edge(self, k: int, info: npt.ArrayLike) -> Edge:
        """Edge ``k`` with another information matrix (a step held more loosely); the same checks as
        ``add_edge``."""
        if not 0 <= k < len(self._edges):
            raise ValueError(f"no such edge {k} (the graph has {len(self._edges)})")
        old = self._edges[k]
        e = Edge(old.i, old.j, old.z, _information(info, old.i, old.j), old.robust)
        self._edges[k] = e
        self._write(k, e)
        return e

    def remove_edges(self, indices: Collection[int]) -> None:
        """Drop the edges at ``indices`` (a closure the solve found wrong); the others keep their order."""
        drop = set(indices)
        if any(not 0 <= k < len(self._edges) for k in drop):
            raise ValueError(f"no such edge among {sorted(drop)} (the graph has {len(self._edges)})")
        m = len(self._edges)
        keep = np.ones(m, dtype=bool)
        keep[list(drop)] = False
        self._edges = [ed for k, ed in enumerate(self._edges) if k not in drop]
        n = len(self._edges)
        for name in ("_ii", "_jj", "_zz", "_om", "_robust"):
            arr = getattr(self, name)
            arr[:n] = arr[:m][keep]

    # -- the solve ----------------------------------------------------------------------------------

    @staticmethod
    def _error(xi: Pose, xj: Pose, z: Pose) -> tuple[F64, F64, F64]:
        """The edge's error and its Jacobians with respect to x_i and x_j (Grisetti et al. eq. 30-31)."""
        ci, si = math.cos(xi[2]), math.sin(xi[2])
        cz, sz = math.cos(z[2]), math.sin(z[2])
        dx, dy = xj[0] - xi[0], xj[1] - xi[1]
        rit = np.array([[ci, si], [-si, ci]])  # R_i^T
        rzt = np.array([[cz, sz], [-sz, cz]])  # R_z^T
        t = rzt @ (rit @ np.array([dx, dy]) - np.array([z[0], z[1]]))
        e = np.array([t[0], t[1], wrap(xj[2] - xi[2] - z[2])])
        drit = np.array([[-si, ci], [-ci, -si]])  # d R_i^T / d theta_i
        a = np.zeros((3, 3))
        a[:2, :2] = -rzt @ rit
        a[:2, 2] = rzt @ drit @ np.array([dx, dy])
        a[2, 2] = -1.0
        b = np.zeros((3, 3))
        b[:2, :2] = rzt @ rit
        b[2, 2] = 1.0
        return e, a, b

    def chi2(self, poses: Sequence[Pose] | None = None) -> float:
        """Sum of e^T Omega e over the edges at ``poses`` (default: the graph's)."""
        ps = self.poses if poses is None else poses
        total = float(self.errors(ps).sum())
        for p in self.priors:
            dx, dy = ps[p.i][0] - p.xy[0], ps[p.i][1] - p.xy[1]
            total += (dx * dx + dy * dy) / (p.sigma * p.sigma)
        return total

    def optimize(self, *, fixed: int | None = 0, iterations: int = 20, tolerance: float = 1e-9) -> Solve:
        """Gauss-Newton (iteratively reweighted for robust edges) with node ``fixed`` held still
        (``None``: none, for a graph its priors anchor). The graph's poses are replaced by the
        solution; nodes no edge reaches keep their guess."""
        n = len(self.poses)
        if fixed is not None and not 0 <= fixed < n:
            raise ValueError(f"fixed node {fixed}: no such node (the graph has {n})")
        poses = list(self.poses)
        before = self.chi2(poses)
        if not self._edges and not self.priors:
            return Solve(poses, 0, before, before, True)
        if not self._edges:  # priors only: each node with one goes to its mean
            self.poses = _prior_means(poses, self.priors)
            return Solve(self.poses, 1, before, self.chi2(self.poses), True)
        ii, jj, zz, om, robust = self._packed()
        x = np.array(poses, dtype=np.float64)
        # Sparse layout of H: the 3x3 blocks (i,i), (i,j), (j,i), (j,j) of every edge, then the fixed
        # node's and the loose nodes' diagonals; duplicates are summed by the COO -> CSC conversion.
        r3 = np.arange(3)
        blk_r = (3 * np.stack((ii, ii, jj, jj), axis=1))[:, :, None, None] + r3[None, None, :, None]
        blk_c = (3 * np.stack((ii, jj, ii, jj), axis=1))[:, :, None, None] + r3[None, None, None, :]
        blk_r, blk_c = np.broadcast_to(blk_r, (len(ii), 4, 3, 3)), np.broadcast_to(blk_c, (len(ii), 4, 3, 3))
        done = 0
        converged = False
        w = np.ones(len(self._edges))
        for step in range(1, iterations + 1):
            done = step
            e, a, b = _errors(x[ii], x[jj], zz)
            if robust.any():
                s = np.einsum("ek,ekl,el->e", e, om, e)
                w = np.where(robust, 1.0 / (1.0 + s / (self.cauchy_c * self.cauchy_c)), 1.0)
            wom = om * w[:, None, None]
            at_om = np.einsum("eki,ekl->eil", a, wom)  # A^T Omega
            bt_om = np.einsum("eki,ekl->eil", b, wom)
            blocks = np.stack((at_om @ a, at_om @ b, bt_om @ a, bt_om @ b), axis=1)  # (E, 4, 3, 3): ii, ij, ji, jj
            g = np.zeros(3 * n)
            np.add.at(g, (3 * ii[:, None] + r3).ravel(), np.einsum("eil,el->ei", at_om, e).ravel())
            np.add.at(g, (3 * jj[:, None] + r3).ravel(), np.einsum("eil,el->ei", bt_om, e).ravel())
            rows, cols, vals = blk_r.ravel(), blk_c.ravel(), blocks.ravel()
            if self.priors:  # e = x_i - z on x and y: J = I, so Omega on the diagonal, Omega e in g
                pi = np.array([p.i for p in self.priors], dtype=np.int64)
                pw = np.array([1.0 / (p.sigma * p.sigma) for p in self.priors])
                pe = x[pi, :2] - np.array([p.xy for p in self.priors])
                prow = np.concatenate((3 * pi, 3 * pi + 1))
                rows = np.concatenate((rows, prow))
                cols = np.concatenate((cols, prow))
                vals = np.concatenate((vals, pw, pw))
                np.add.at(g, prow, np.concatenate((pw * pe[:, 0], pw * pe[:, 1])))
            if fixed is not None:
                # The fixed node: its rows and columns out, identity on its diagonal (its step is zero).
                keep = ~(((rows // 3) == fixed) | ((cols // 3) == fixed))
                rows, cols, vals = rows[keep], cols[keep], vals[keep]
                g[3 * fixed : 3 * fixed + 3] = 0.0
            diag = np.zeros(3 * n)
            np.add.at(diag, rows[rows == cols], vals[rows == cols])
            extra = np.flatnonzero(diag == 0.0)  # the fixed node and nodes nothing touches: held still
            # A whisker of damping: a graph anchored by position priors alone leaves its heading free
            # where too few priors pin it; the step there stays (near) zero instead of undefined.
            rows = np.concatenate((rows, np.arange(3 * n)))
            cols = np.concatenate((cols, np.arange(3 * n)))
            vals = np.concatenate((vals, np.full(3 * n, 1e-9)))
            from scipy import sparse  # here, not at import: ~29 MB of RSS an agent without a solve
            from scipy.sparse.linalg import spsolve  # (closures off, or none yet) does not pay

            h = sparse.csc_matrix(
                (
                    np.concatenate((vals, np.ones(len(extra)))),
                    (np.concatenate((rows, extra)), np.concatenate((cols, extra))),
                ),
                shape=(3 * n, 3 * n),
            )
            # H is symmetric: ordered by minimum degree on its pattern (H^T + H), SuperLU's fill-in and
            # time are half COLAMD's (the default, for any square matrix) on intel's final graph.
            dx = np.asarray(spsolve(h, -g, permc_spec="MMD_AT_PLUS_A"), dtype=np.float64).reshape(n, 3)
            if not np.isfinite(dx).all():  # a singular system: keep the last poses
                break
            x = x + dx
            th = x[:, 2]
            x[:, 2] = np.where(np.abs(th) > math.pi, np.remainder(th + math.pi, 2.0 * math.pi) - math.pi, th)
            if float(np.max(np.abs(dx))) < tolerance:
                converged = True
                break
        poses = [(float(p[0]), float(p[1]), float(p[2])) for p in x]
        self.poses = poses
        outliers = tuple(int(k) for k in np.flatnonzero(robust & (w < 0.5)))
        return Solve(poses, done, before, self.chi2(poses), converged, outliers)

    def errors(self, poses: Sequence[Pose] | None = None) -> F64:
        """Each edge's e^T Omega e at ``poses`` (default: the graph's; no kernel), in edge order."""
        if not self._edges:
            return np.zeros(0)
        x = np.array(self.poses if poses is None else poses, dtype=np.float64)
        ii, jj, zz, om, _ = self._packed()
        e, _, _ = _errors(x[ii], x[jj], zz)
        out: F64 = np.einsum("ek,ekl,el->e", e, om, e)
        return out


def _information(info: npt.ArrayLike, i: int, j: int) -> F64:
    """An edge's information matrix, checked: finite, symmetric 3x3, positive definite."""
    om = np.array(info, dtype=np.float64)
    if om.shape != (3, 3) or not np.all(np.isfinite(om)) or not np.allclose(om, om.T, atol=1e-9):
        raise ValueError(f"edge {i}->{j}: information must be a finite symmetric 3x3 matrix")
    try:
        np.linalg.cholesky(om)
    except np.linalg.LinAlgError:
        raise ValueError(f"edge {i}->{j}: information must be positive definite") from None
    return om


def _prior_means(poses: list[Pose], priors: list[Prior]) -> list[Pose]:
    """Each node with priors at their information-weighted mean position (heading unchanged)."""
    acc: dict[int, tuple[float, float, float]] = {}
    for p in priors:
        w = 1.0 / (p.sigma * p.sigma)
        sx, sy, sw = acc.get(p.i, (0.0, 0.0, 0.0))
        acc[p.i] = (sx + w * p.xy[0], sy + w * p.xy[1], sw + w)
    out = list(poses)
    for i, (sx, sy, sw) in acc.items():
        out[i] = (sx / sw, sy / sw, poses[i][2])
    return out


def _errors(xi: F64, xj: F64, z: F64) -> tuple[F64, F64, F64]:
    """``PoseGraph._error`` for many edges at once: errors (E, 3) and Jacobians (E, 3, 3)."""
    ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    # R_i^T d, then R_z^T (R_i^T d - t_z)
    u, v = ci * dx + si * dy - z[:, 0], -si * dx + ci * dy - z[:, 1]
    e = np.column_stack(
        (
            cz * u + sz * v,
            -sz * u + cz * v,
            np.remainder(xj[:, 2] - xi[:, 2] - z[:, 2] + math.pi, 2.0 * math.pi) - math.pi,
        )
    )
    # R_z^T R_i^T = R(-(theta_i + theta_z))
    c, s = np.cos(xi[:, 2] + z[:, 2]), np.sin(xi[:, 2] + z[:, 2])
    # d(R_i^T d)/d theta_i = (-si dx + ci dy, -ci dx - si dy); then R_z^T of that
    p, q = -si * dx + ci * dy, -ci * dx - si * dy
    m = len(e)
    a = np.zeros((m, 3, 3))
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1] = -c, -s, s, -c
    a[:, 0, 2], a[:, 1, 2] = cz * p + sz * q, -sz * p + cz * q
    a[:, 2, 2] = -1.0
    b = np.zeros((m, 3, 3))
    b[:, 0, 0], b[:, 0, 1], b[:, 1, 0], b[:, 1, 1] = c, s, -s, c
    b[:, 2, 2] = 1.0
    return e, a, b
