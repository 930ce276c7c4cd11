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
import threading

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
    by ``pad`` zero cells on each side so a lookup with a block's offset never leaves the array.
    Levels are built when first asked for (``level``): a small window's search never needs the top
    ones (the final pass's 0.3 m windows stop at level 4 of 6)."""

    def __init__(self, field: F32, origin: tuple[float, float], resolution: float, depth: int = 6) -> None:
        if depth < 1 or field.ndim != 2:
            raise ValueError("need depth >= 1 and a 2D field")
        self.resolution = resolution
        self.origin = origin
        self.depth = depth
        self.shape = (int(field.shape[0]), int(field.shape[1]))
        self.pad = pad = 1 << depth
        h, w = self.shape
        base = np.zeros((h + 2 * pad, w + 2 * pad), dtype=np.float32)
        base[pad : pad + h, pad : pad + w] = field
        self._levels: list[F32] = [base]
        self._lock = threading.Lock()  # a drawn submap may be searched from two threads

    @property
    def levels(self) -> list[F32]:
        """Every level, 0 to ``depth`` (built now if not yet)."""
        self.level(self.depth)
        return self._levels

    def level(self, d: int) -> F32:
        """Level ``d`` (0: the padded field), built with those below it if not yet."""
        if d < len(self._levels):
            return self._levels[d]
        if not 0 <= d <= self.depth:
            raise ValueError(f"no level {d}: the levels run 0 to {self.depth}")
        with self._lock:
            while len(self._levels) <= d:
                cur = self._levels[-1]
                s = 1 << (len(self._levels) - 1)  # the window grows from s to 2s: max of the s-window here and s on
                across = np.empty_like(cur)
                np.maximum(cur[:, :-s], cur[:, s:], out=across[:, :-s])
                across[:, -s:] = cur[:, -s:]
                nxt = np.empty_like(cur)
                np.maximum(across[:-s, :], across[s:, :], out=nxt[:-s, :])
                nxt[-s:, :] = across[-s:, :]
                self._levels.append(nxt)
        return self._levels[d]


def search(
    grids: PrecomputedGrids,
    points: F64,
    guess: Pose,
    window_xy: float,
    window_theta: float,
    min_score: float,
    angle_step: float = math.radians(0.5),
    max_batches: int = 2000,
) -> tuple[Pose, float] | None:
    """The best sensor pose for ``points`` (sensor frame) within ``window_xy`` / ``window_theta``
    of ``guess``, or None when no candidate scores above ``min_score`` or when ``max_batches``
    expansions left the search undecided (the scan fits many places about as well).

    Depth first, in batches: the deepest level with candidates left gives up its ``_BATCH`` best,
    all expanded in one vectorised lookup (one Python step per batch, not per block)."""
    if not (angle_step > 0 and math.isfinite(angle_step)):
        raise ValueError(f"angle_step must be > 0, got {angle_step!r}")
    if len(points) == 0:
        return None
    res, pad = grids.resolution, grids.pad
    ox, oy = grids.origin
    n_lin = max(0, math.ceil(window_xy / res))
    n_ang = max(0, round(window_theta / angle_step))
    # Offsets (in cells) run over [0, span) from the window's low corner; blocks of ``top`` tile them.
    # A small window starts at the level whose one block covers it (the levels above would only split
    # that block's bound again): the same answer, fewer steps.
    span = 2 * n_lin + 1
    depth = min(grids.depth, max(1, (span - 1).bit_length()))
    top = 1 << depth
    nblk = -(-span // top)
    thetas = guess[2] + angle_step * np.arange(-n_ang, n_ang + 1, dtype=np.float64)
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    px, py = points[None, :, 0], points[None, :, 1]
    cols: I64 = np.floor((guess[0] + c * px - s * py - ox) / res).astype(np.int64) - n_lin + pad
    rows: I64 = np.floor((guess[1] + s * px + c * py - oy) / res).astype(np.int64) - n_lin + pad
    n_pts = float(len(points))
    hh, ww = grids.level(0).shape
    # Each rotation's points' extent, and their flat indices: a batch whose every shifted point lies
    # inside the levels (the usual case) is looked up without masks or clips, and sums the same values.
    rmin, rmax = rows.min(axis=1), rows.max(axis=1)
    cmin, cmax = cols.min(axis=1), cols.max(axis=1)
    flat0: I64 = rows * ww + cols

    def score(level: int, k: I64, dr: I64, dc: I64) -> F64:
        """Mean of level ``level`` under rotation ``k``'s points shifted by (dr, dc), per candidate."""
        if (
            int((rmin[k] + dr).min()) >= 0
            and int((rmax[k] + dr).max()) < hh
            and int((cmin[k] + dc).min()) >= 0
            and int((cmax[k] + dc).max()) < ww
        ):
            inner = flat0[k]
            inner += (dr * ww + dc)[:, None]
            fast: F64 = grids.level(level).reshape(-1).take(inner).sum(axis=1, dtype=np.float64) / n_pts
            return fast
        rr = rows[k] + dr[:, None]
        cc = cols[k] + dc[:, None]
        ok = (rr >= 0) & (rr < hh) & (cc >= 0) & (cc < ww)
        flat = np.clip(rr, 0, hh - 1) * ww + np.clip(cc, 0, ww - 1)
        vals = grids.level(level).reshape(-1)[flat]
        out: F64 = np.where(ok, vals, np.float32(0.0)).sum(axis=1, dtype=np.float64) / n_pts
        return out

    # The top level: every block of every rotation.
    gk, gr, gc = np.meshgrid(np.arange(len(thetas)), np.arange(nblk) * top, np.arange(nblk) * top, indexing="ij")
    k0: I64 = gk.ravel().astype(np.int64)
    r0: I64 = gr.ravel().astype(np.int64)
    c0: I64 = gc.ravel().astype(np.int64)
    # Scored in chunks: a 10 m, 35 deg window has ~7000 top blocks, times ~150 points each.
    b0 = np.concatenate(
        [score(depth, k0[i : i + _CHUNK], r0[i : i + _CHUNK], c0[i : i + _CHUNK]) for i in range(0, len(k0), _CHUNK)]
    )
    # Per level, the candidates still to expand, sorted by bound (best last).
    frontier: list[tuple[F64, I64, I64, I64]] = [(np.zeros(0), k0[:0], r0[:0], c0[:0])] * (depth + 1)
    order = np.argsort(b0, kind="stable")
    frontier[depth] = (b0[order], k0[order], r0[order], c0[order])
    best_score = min_score
    best: tuple[int, int, int] | None = None
    batches = 0
    while True:
        batches += 1
        if batches > max_batches:
            # So many blocks still bound above the best found that the scan fits many places about
            # as well: not a distinctive match, and the search is bounded in time (~0.5 s here).
            return None
        level = next((d for d in range(1, depth + 1) if len(frontier[d][0])), -1)
        if level < 0:
            break
        fb, fk, fr, fc = frontier[level]
        take = slice(max(0, len(fb) - _BATCH), len(fb))
        bb, kk, rr_, cc_ = fb[take], fk[take], fr[take], fc[take]
        frontier[level] = (fb[: take.start], fk[: take.start], fr[: take.start], fc[: take.start])
        live = bb > best_score
        if not live.any():
            # Sorted: everything left at this level is no better.
            frontier[level] = (fb[:0], fk[:0], fr[:0], fc[:0])
            continue
        kk, rr_, cc_ = kk[live], rr_[live], cc_[live]
        half = 1 << (level - 1)
        ck = np.repeat(kk, 4)
        cr = (rr_[:, None] + np.array([0, 0, half, half])).ravel()
        cc2 = (cc_[:, None] + np.array([0, half, 0, half])).ravel()
        inside = (cr < span) & (cc2 < span)
        ck, cr, cc2 = ck[inside], cr[inside], cc2[inside]
        if not len(ck):
            continue
        kb = score(level - 1, ck, cr, cc2)
        if level - 1 == 0:
            i = int(np.argmax(kb))
            if kb[i] > best_score:
                best_score, best = float(kb[i]), (int(ck[i]), int(cr[i]), int(cc2[i]))
            continue
        keep = kb > best_score
        if not keep.any():
            continue
        nb = np.concatenate((frontier[level - 1][0], kb[keep]))
        nk = np.concatenate((frontier[level - 1][1], ck[keep]))
        nr = np.concatenate((frontier[level - 1][2], cr[keep]))
        nc = np.concatenate((frontier[level - 1][3], cc2[keep]))
        o = np.argsort(nb, kind="stable")
        frontier[level - 1] = (nb[o], nk[o], nr[o], nc[o])
    if best is None:
        return None
    k, r, cl = best
    pose = (guess[0] + (cl - n_lin) * res, guess[1] + (r - n_lin) * res, float(thetas[k]))
    return pose, best_score


_BATCH = 32
"""Candidates expanded per step of the search."""
_CHUNK = 1024
"""Top-level blocks scored per lookup (bounds the temporary arrays)."""
