"""Branch-and-bound correlative scan matching over a wide window (loop closure's verification).

After Hess, Kohler, Rapp and Andor, "Real-Time Loop Closure in 2D LIDAR SLAM" (ICRA 2016),
section V: a scan's score at a translation is the mean likelihood-field value under its points.
For a block of ``2^d x 2^d`` translations, the mean of the field's *sliding-window* maxima (each
cell holds the maximum over the ``2^d x 2^d`` cells above and to the right of it) is an upper
bound of the score of every translation in the block. So a depth-first search that starts with
the whole window in blocks of ``2^D`` cells, expands the best block first and drops every block
whose bound is not above the best leaf found so far (or the caller's ``min_score``) finds the
same best translation as scoring every one of them, visiting a small share.

Rotations are enumerated (the bound holds per rotation): every ``angle_step`` in the window.
The answer is on the cell lattice and the angle step; the caller refines it (Gauss-Newton on the
interpolated field, point-to-line).

    grids = PrecomputedGrids(field, origin, resolution, depth=6)   # once per submap
    found = search(grids, points, guess, window_xy=4.0, window_theta=0.5, min_score=0.5)
    # -> (pose, score) of the best sensor pose, or None when nothing scores min_score

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["PrecomputedGrids", "search"]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
Pose = tuple[float, float, float]


class PrecomputedGrids:
    """The field and its sliding-window maxima for windows of 1, 2, 4, ... ``2^depth`` cells.

    Level ``d``: ``level[d][r, c] = max(field[r : r + 2^d, c : c + 2^d])``. Every level is padded
    by ``pad`` zero cells on each side so a lookup with a block's offset never leaves the array."""

    def __init__(self, field: F32, origin: tuple[float, float], resolution: float, depth: int = 6) -> None:
        if depth < 0 or field.ndim != 2:
            raise ValueError("need depth >= 0 and a 2D field")
        self.resolution = resolution
        self.origin = origin
        self.depth = depth
        self.shape = (int(field.shape[0]), int(field.shape[1]))
        self.pad = pad = 1 << depth
        h, w = self.shape
        base = np.zeros((h + 2 * pad, w + 2 * pad), dtype=np.float32)
        base[pad : pad + h, pad : pad + w] = field
        self.levels: list[F32] = [base]
        cur = base
        for d in range(depth):
            s = 1 << d  # the window grows from s to 2s: max of the s-window here and s cells on
            nxt = cur.copy()
            np.maximum(nxt[:, :-s], cur[:, s:], out=nxt[:, :-s])
            np.maximum(nxt[:-s, :], nxt[s:, :].copy(), out=nxt[:-s, :])
            self.levels.append(nxt)
            cur = nxt


@dataclass(frozen=True, slots=True)
class _Scan:
    rows: I64  # the rotated points' cells (padded array coordinates) at the window's lowest offset
    cols: I64
    theta: float


def search(
    grids: PrecomputedGrids,
    points: F64,
    guess: Pose,
    window_xy: float,
    window_theta: float,
    min_score: float,
    angle_step: float = math.radians(0.5),
) -> tuple[Pose, float] | None:
    """The best sensor pose for ``points`` (sensor frame) within ``window_xy`` / ``window_theta``
    of ``guess``, or None when no candidate scores above ``min_score``."""
    if len(points) == 0:
        return None
    res, pad, depth = grids.resolution, grids.pad, grids.depth
    ox, oy = grids.origin
    h, w = grids.shape
    n_lin = max(0, math.ceil(window_xy / res))
    n_ang = max(0, round(window_theta / angle_step))
    top = 1 << depth
    # Offsets (in cells) run over [-n_lin, n_lin]; blocks of ``top`` cells tile them from the low corner.
    span = 2 * n_lin + 1
    nblk = -(-span // top)
    scans: list[_Scan] = []
    px, py = points[:, 0], points[:, 1]
    for a in range(-n_ang, n_ang + 1):
        th = guess[2] + a * angle_step
        c, s = math.cos(th), math.sin(th)
        wx = guess[0] + c * px - s * py
        wy = guess[1] + s * px + c * py
        col = np.floor((wx - ox) / res).astype(np.int64) - n_lin + pad
        row = np.floor((wy - oy) / res).astype(np.int64) - n_lin + pad
        # A point whose whole window lies off the grid never scores: drop it from the lookups (it
        # still counts in the mean, as a zero).
        keep = (col + span > pad - top) & (col < pad + w) & (row + span > pad - top) & (row < pad + h)
        scans.append(_Scan(row[keep], col[keep], th))
    n_pts = float(len(points))
    hi = grids.levels[0].shape

    def score(level: int, k: int, dr: I64, dc: I64) -> F64:
        """Mean of level ``level`` over scan ``k``'s points shifted by each (dr, dc)."""
        sc = scans[k]
        grid = grids.levels[level]
        rr = sc.rows[None, :] + dr[:, None]
        cc = sc.cols[None, :] + dc[:, None]
        ok = (rr >= 0) & (rr < hi[0]) & (cc >= 0) & (cc < hi[1])
        vals = np.where(ok, grid[np.clip(rr, 0, hi[0] - 1), np.clip(cc, 0, hi[1] - 1)], 0.0)
        out: F64 = vals.sum(axis=1, dtype=np.float64) / n_pts
        return out

    # The top level: every block of every rotation, best first.
    gr, gc = np.meshgrid(np.arange(nblk) * top, np.arange(nblk) * top, indexing="ij")
    br: I64 = gr.ravel().astype(np.int64)
    bc: I64 = gc.ravel().astype(np.int64)
    stack: list[tuple[float, int, int, int, int]] = []  # (bound, depth, rotation, row offset, col offset)
    for k in range(len(scans)):
        for sc_, r_, c_ in zip(score(depth, k, br, bc), br, bc, strict=True):
            stack.append((float(sc_), depth, k, int(r_), int(c_)))
    stack.sort(key=lambda e: e[0])  # a stack: the best is popped first
    best_score = min_score
    best: tuple[int, int, int] | None = None
    while stack:
        bound, d, k, r0, c0 = stack.pop()
        if bound <= best_score:
            continue
        if d == 0:
            if r0 < span and c0 < span:
                best_score, best = bound, (k, r0, c0)
            continue
        half = 1 << (d - 1)
        dr = np.array([r0, r0, r0 + half, r0 + half], dtype=np.int64)
        dc = np.array([c0, c0 + half, c0, c0 + half], dtype=np.int64)
        inside = (dr < span) & (dc < span)
        dr, dc = dr[inside], dc[inside]
        if not len(dr):
            continue
        kids = score(d - 1, k, dr, dc)
        order = np.argsort(kids)
        for i in order:
            if kids[i] > best_score:
                stack.append((float(kids[i]), d - 1, k, int(dr[i]), int(dc[i])))
    if best is None:
        return None
    k, r0, c0 = best
    pose = (guess[0] + (c0 - n_lin) * res, guess[1] + (r0 - n_lin) * res, scans[k].theta)
    return pose, best_score
