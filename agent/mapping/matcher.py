"""Scan-to-map matching: correlative search coarse to fine, then Gauss-Newton refinement.

``match_scan(grid, points, guess, config)`` finds the sensor pose that puts the scan's points on
the map's walls, searching a window around ``guess`` (the fused pose, or odometry):

1. **Coarse**: every rotation in ``±search_theta`` (``coarse_angle_step``) against every
   translation in ``±search_xy`` in steps of one coarse cell (``GridConfig.coarse`` cells), scored
   on the max-pooled likelihood field. Max-pooling makes the coarse score an (almost) upper bound
   of the fine one over the coarse cell, so the best coarse candidate is where the fine optimum is.
2. **Fine**: around the best coarse candidate, rotations one coarse step either side in
   ``fine_angle_step`` and translations cell by cell, on the full-resolution field.
3. **Refinement**: Gauss-Newton on the bilinearly interpolated field (Kohlbrecher et al.'s Hector
   formulation: minimise sum (1 - M(S_i(xi)))^2), sub-cell accurate.

Scores are the mean field value at the points (0: none on a known wall, 1: all of them), less a
Gaussian motion prior on the deviation from the guess (Olson's correlative matching): a long
corridor scores the same all along, and the prior keeps the guess there.

``icp_refine`` then refines against a ``LocalMap`` (the last keyframes' points and normals):
point-to-line Gauss-Newton with the same prior, so a direction the points do not constrain stays
at the guess while the others follow the walls. ``icp_refine_many`` runs many such problems that do
not depend on one another (a replay's final pass: thousands of scan pairs) as one, array-wide.
The caller decides what a poor score means (the mapper falls back to odometry).

Pure numpy; no I/O.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.grid import LogOddsGrid

__all__ = [
    "FieldMap",
    "IcpResult",
    "LocalMap",
    "Match",
    "MatchConfig",
    "field_score",
    "icp_refine",
    "icp_refine_many",
    "match_scan",
    "refine",
    "scan_normals",
]

FloatArray = npt.NDArray[np.float64]
Pose = tuple[float, float, float]


class FieldMap(Protocol):
    """What the field's scoring and refinement read: a likelihood field (row ``v``, column ``u``;
    cell (0, 0) has its corner at ``origin``) and its cell size. A ``LogOddsGrid`` is one; so is a
    drawn submap's field kept alone (``closure.SubmapField``)."""

    @property
    def field(self) -> npt.NDArray[np.float32]: ...

    @property
    def origin(self) -> tuple[float, float]: ...

    @property
    def resolution(self) -> float: ...


@dataclass(frozen=True, slots=True)
class MatchConfig:
    search_xy: float = 0.3  # m, half-width of the translation window around the guess
    search_theta: float = math.radians(15.0)  # rad, half-width of the rotation window
    coarse_angle_step: float = math.radians(1.5)
    fine_angle_step: float = math.radians(0.375)
    refine_iterations: int = 8
    candidates: int = 1  # coarse candidates searched finely (2 costs twice the time for little gain measured)
    prior_weight: float = 0.3  # score penalty per unit of squared Mahalanobis deviation from the guess / 2
    prior_sigma_xy: float = 0.1  # m, default motion-prior sd (callers pass their own, e.g. from odometry)
    prior_sigma_theta: float = math.radians(5.0)

    def __post_init__(self) -> None:
        if self.search_xy < 0 or self.search_theta < 0:
            raise ValueError("search windows must be >= 0")
        if not (self.coarse_angle_step > 0 and 0 < self.fine_angle_step <= self.coarse_angle_step):
            raise ValueError("need 0 < fine_angle_step <= coarse_angle_step")


@dataclass(frozen=True, slots=True)
class Match:
    pose: Pose  # the sensor pose found
    score: float  # mean likelihood of the points at ``pose`` (0..1)
    guess_score: float  # the same at the guess


def _lookup(field: npt.NDArray[np.float32], rows: npt.NDArray[np.int64], cols: npt.NDArray[np.int64]) -> FloatArray:
    h, w = field.shape
    ok = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    flat = np.where(ok, rows * w + cols, 0)
    return np.where(ok, field.reshape(-1)[flat], 0.0).astype(np.float64)


def _transform(points: FloatArray, x: float, y: float, th: float) -> FloatArray:
    c, s = math.cos(th), math.sin(th)
    return np.column_stack((x + c * points[:, 0] - s * points[:, 1], y + s * points[:, 0] + c * points[:, 1]))


def field_score(grid: FieldMap, points: FloatArray, pose: Pose) -> float:
    """Mean field value (bilinearly interpolated) of ``points`` (sensor frame) seen from ``pose``."""
    if len(points) == 0:
        return 0.0
    return _score_at(grid.field, points[:, 0], points[:, 1], pose, grid.origin, grid.resolution)


def _search(
    field: npt.NDArray[np.float32],
    points: FloatArray,
    cell_size: float,
    origin: tuple[float, float],
    x: float,
    y: float,
    thetas: FloatArray,
    offsets: npt.NDArray[np.int64],
    penalty: FloatArray,
    top: int = 1,
) -> list[tuple[int, int, float]]:
    """The ``top`` best (theta index, offset index, score) of rotations x integer cell offsets on ``field``
    (a likelihood field: values in [0, 1])."""
    if top == 1:
        # Only the candidates the motion prior leaves a chance, when they are few (_search_best).
        chance = penalty <= float(penalty.min()) + _SCORE_SPAN
        if _PRUNE_SHARE * int(np.count_nonzero(chance)) <= chance.size:
            return [_search_best(field, points, cell_size, origin, x, y, thetas, offsets, penalty, chance)]
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    px, py = points[None, :, 0], points[None, :, 1]
    cols = np.floor((x + c * px - s * py - origin[0]) / cell_size).astype(np.int64)  # (A, N)
    rows = np.floor((y + s * px + c * py - origin[1]) / cell_size).astype(np.int64)
    h, w = field.shape
    oc, orr = offsets[:, 0], offsets[:, 1]
    if (
        int(rows.min()) + int(orr.min()) >= 0
        and int(rows.max()) + int(orr.max()) < h
        and int(cols.min()) + int(oc.min()) >= 0
        and int(cols.max()) + int(oc.max()) < w
    ):
        # Every candidate inside the grid (the usual case): one flat index per point and per offset,
        # offsets outermost (each offset a scalar added to one long contiguous run).
        rows *= w
        rows += cols
        r = (orr * w + oc)[:, None, None] + rows[None, :, :]  # (T, A, N)
    else:
        # Clip instead of masking (cheaper): the grid always extends past every integrated scan, so
        # its edge cells are empty and a point beyond the edge reads 0 either way.
        r = np.clip(orr[:, None, None] + rows[None, :, :], 0, h - 1)
        q = np.clip(oc[:, None, None] + cols[None, :, :], 0, w - 1)
        r *= w
        r += q
    # Each candidate's sum over its points in point order, as from an (A, T, N) array; then (A, T).
    scores = np.ascontiguousarray(np.add.reduce(field.reshape(-1).take(r), axis=2, dtype=np.float32).T)
    scores /= r.shape[2]  # the mean, as np.mean computes it
    scores = scores - penalty  # (A, T)
    flat = scores.ravel()
    if top == 1:
        b = int(flat.argmax())
        return [(*divmod(b, scores.shape[1]), float(flat[b]))]
    k = min(top, flat.size)
    best = np.argpartition(-flat, k - 1)[:k] if k < flat.size else np.arange(flat.size)
    best = best[np.argsort(-flat[best], kind="stable")]
    return [(*divmod(int(b), scores.shape[1]), float(flat[b])) for b in best]


def _search_best(
    field: npt.NDArray[np.float32],
    points: FloatArray,
    cell_size: float,
    origin: tuple[float, float],
    x: float,
    y: float,
    thetas: FloatArray,
    offsets: npt.NDArray[np.int64],
    penalty: FloatArray,
    chance: npt.NDArray[np.bool_],
) -> tuple[int, int, float]:
    """``_search`` with ``top`` 1, scoring only the candidates the motion prior leaves a chance: a score
    is a mean field value (in [0, 1]) less the candidate's penalty, so the least penalised candidate
    scores at least minus its penalty, and a candidate penalised more than 1 beyond it scores less than
    that whatever the field says. Those are not scored; the rest are, each exactly as ``_search`` scores
    it (its points' sum in point order, / N, less its penalty), and the first best in the same (rotation,
    offset) order wins: the same answer. With odometry's tight prior a handful of the hundreds.
    ``chance``: (A, T), the candidates to score."""
    va, vt = np.nonzero(chance)  # row-major: _search's order
    used = chance.any(axis=1)
    which = (np.cumsum(used) - 1)[va]  # each candidate's row among the rotations used
    th = thetas[used]
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    px, py = points[None, :, 0], points[None, :, 1]
    cols = np.floor((x + c * px - s * py - origin[0]) / cell_size).astype(np.int64)[which]  # (V, N)
    rows = np.floor((y + s * px + c * py - origin[1]) / cell_size).astype(np.int64)[which]
    h, w = field.shape
    oc, orr = offsets[vt, 0][:, None], offsets[vt, 1][:, None]
    rows += orr
    cols += oc
    if int(rows.min()) >= 0 and int(rows.max()) < h and int(cols.min()) >= 0 and int(cols.max()) < w:
        rows *= w
        rows += cols
    else:  # as _search: clipped (the grid's edge cells are empty)
        np.clip(rows, 0, h - 1, out=rows)
        np.clip(cols, 0, w - 1, out=cols)
        rows *= w
        rows += cols
    scores = np.add.reduce(field.reshape(-1).take(rows), axis=1, dtype=np.float32)
    scores /= rows.shape[1]  # the mean, as np.mean computes it
    final = scores - penalty[va, vt]
    b = int(final.argmax())
    return int(va[b]), int(vt[b]), float(final[b])


_SCORE_SPAN = 1.0 + 1e-3
"""How far a likelihood field's mean value can range (0 to 1), with room for float32 rounding."""
_PRUNE_SHARE = 4
"""The correlative search scores only the candidates with a chance when they are at most 1 in this many
(beyond that, scoring them all in one broadcast is as cheap)."""


@functools.cache
def _grid_offsets(lo: int, hi: int) -> npt.NDArray[np.int64]:
    """Every (col, row) offset in ``[lo, hi]^2``, rows outer (read-only: cached, two windows a scan)."""
    k = np.arange(lo, hi + 1, dtype=np.int64)
    qq, rr = np.meshgrid(k, k)
    out = np.column_stack((qq.ravel(), rr.ravel()))
    out.flags.writeable = False
    return out


def match_scan(
    grid: LogOddsGrid,
    points: FloatArray,
    guess: Pose,
    config: MatchConfig | None = None,
    prior: tuple[float, float] | None = None,
) -> Match:
    """Best sensor pose for ``points`` (sensor frame, (N, 2)) near ``guess``; see the module docstring.

    ``prior``: (sd xy m, sd theta rad) of the guess (a Gaussian motion prior, Olson 2009): the score
    is penalised by ``prior_weight * d^2 / 2`` for a candidate ``d`` standard deviations away."""
    cfg = config or MatchConfig()
    sxy, sth = prior if prior is not None else (cfg.prior_sigma_xy, cfg.prior_sigma_theta)
    sxy, sth = max(sxy, 1e-3), max(sth, 1e-4)
    gx, gy, gth = guess
    guess_score = field_score(grid, points, guess)
    if len(points) == 0 or grid.empty:
        return Match(guess, guess_score, guess_score)
    res = grid.resolution
    cc = grid.config.coarse
    big = res * cc
    w = cfg.prior_weight

    # 1. coarse
    na = round(cfg.search_theta / cfg.coarse_angle_step)
    dth = cfg.coarse_angle_step * np.arange(-na, na + 1, dtype=np.float64)
    nt = math.ceil(cfg.search_xy / big)
    offs = _grid_offsets(-nt, nt)
    pen_t = (offs[:, 0] ** 2 + offs[:, 1] ** 2) * (big / sxy) ** 2
    pen_a = (dth / sth) ** 2
    pen = 0.5 * w * (pen_a[:, None] + pen_t[None, :])
    coarse = _search(grid.coarse_field, points, big, grid.origin, gx, gy, gth + dth, offs, pen, top=cfg.candidates)

    # 2. fine, around each of the best coarse candidates: one coarse step of rotation either side,
    # the coarse cell and a cell around it (a point near a coarse cell's edge may belong to either).
    nf = round(cfg.coarse_angle_step / cfg.fine_angle_step)
    foffs = _grid_offsets(-(cc // 2 + 1), cc // 2 + 1)
    best: tuple[float, Pose] | None = None
    for a, t, _ in coarse:
        cth = gth + float(dth[a])
        cx = gx + float(offs[t, 0]) * big
        cy = gy + float(offs[t, 1]) * big
        fth = cth + cfg.fine_angle_step * np.arange(-nf, nf + 1, dtype=np.float64)
        fx = cx + foffs[:, 0] * res - gx
        fy = cy + foffs[:, 1] * res - gy
        fpen_t = (fx**2 + fy**2) / sxy**2
        fpen_a = ((fth - gth) / sth) ** 2
        fpen = 0.5 * w * (fpen_a[:, None] + fpen_t[None, :])
        fa, ft, fs = _search(grid.field, points, res, grid.origin, cx, cy, fth, foffs, fpen)[0]
        if best is None or fs > best[0]:
            best = (fs, (cx + float(foffs[ft, 0]) * res, cy + float(foffs[ft, 1]) * res, float(fth[fa])))
    assert best is not None
    pose = best[1]

    # 3. refine
    pose, score = _refine(grid, points, pose, cfg.refine_iterations)
    if score < guess_score:  # never worse than where we started
        return Match(guess, guess_score, guess_score)
    return Match(pose, score, guess_score)


def _corners(
    field: npt.NDArray[np.float32], u: FloatArray, v: FloatArray, inside: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(4, N) field values at the cells around continuous cell coords (u, v) (order m00, m10, m01, m11,
    0 outside the field), and the fractional parts fu, fv. ``inside``: the caller knows every point's four
    corners are inside the field (``_inside``), so they are not checked."""
    h, w = field.shape
    uf, vf = np.floor(u), np.floor(v)
    fu, fv = u - uf, v - vf
    u0, v0 = uf.astype(np.int64), vf.astype(np.int64)
    if inside or (
        u0.size and int(u0.min()) >= 0 and int(u0.max()) < w - 1 and int(v0.min()) >= 0 and int(v0.max()) < h - 1
    ):
        # All four corners inside (the usual case): one gather, no masks.
        flat = v0 * w + u0
        idx = np.empty((4, *flat.shape), dtype=np.int64)
        idx[0] = flat
        np.add(flat, 1, out=idx[1])
        np.add(flat, w, out=idx[2])
        np.add(flat, w + 1, out=idx[3])
        m: FloatArray = field.reshape(-1).take(idx).astype(np.float64)
        return m, fu, fv
    m = np.stack(
        (_lookup(field, v0, u0), _lookup(field, v0, u0 + 1), _lookup(field, v0 + 1, u0), _lookup(field, v0 + 1, u0 + 1))
    )
    return m, fu, fv


def _interp(field: npt.NDArray[np.float32], u: FloatArray, v: FloatArray, inside: bool = False) -> FloatArray:
    """Bilinearly interpolated value of ``field`` at continuous cell coords (cell centres at k)."""
    (m00, m10, m01, m11), fu, fv = _corners(field, u, v, inside)
    gu = 1 - fu
    out: FloatArray = (1 - fv) * (gu * m00 + fu * m10) + fv * (gu * m01 + fu * m11)
    return out


def _score_at(
    field: npt.NDArray[np.float32],
    px: FloatArray,
    py: FloatArray,
    pose: Pose,
    origin: tuple[float, float],
    res: float,
    inside: bool = False,
) -> float:
    """``field_score`` on the sensor-frame coordinates ``px``, ``py`` (no (N, 2) intermediates)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    u = (x + c * px - s * py - origin[0]) / res - 0.5
    v = (y + s * px + c * py - origin[1]) / res - 0.5
    # The mean as ndarray.mean computes it (pairwise sum, then / n), without its Python wrapper.
    return float(np.add.reduce(_interp(field, u, v, inside))) / len(px)


def _inside(shape: tuple[int, int], reach: float, x: float, y: float, origin: tuple[float, float], res: float) -> bool:
    """Do the four interpolation corners of every point within ``reach`` (m) of (x, y) lie inside a field
    of ``shape``? With a cell to spare each side for rounding."""
    h, w = shape
    u0 = (x - origin[0]) / res - 0.5
    v0 = (y - origin[1]) / res - 0.5
    r = reach / res
    return u0 - r >= 1.0 and u0 + r <= w - 3.0 and v0 - r >= 1.0 and v0 + r <= h - 3.0


def refine(grid: FieldMap, points: FloatArray, pose: Pose, iterations: int = 8) -> Pose:
    """Gauss-Newton on the interpolated field from ``pose``, with step halving: a step is taken only
    if it raises the mean field value (the field is peaked, so full steps overshoot)."""
    return _refine(grid, points, pose, iterations)[0]


def _refine(grid: FieldMap, points: FloatArray, pose: Pose, iterations: int = 8) -> tuple[Pose, float]:
    """``refine``, and ``field_score`` at the pose it returns (which it computed on the way: -1 when it
    ran no iteration). The halved steps are scored together, in one pass over (4, N) arrays, and the
    field's corners at the pose taken are kept for the next iteration's gradient: element by element
    the same arithmetic as scoring each step alone, so the same answer to the bit."""
    x, y, th = pose
    res = grid.resolution
    origin = grid.origin
    field = grid.field
    px, py = points[:, 0], points[:, 1]
    n = len(px)
    # How far the points reach from the sensor: the corners' bounds are then checked per pose, not per point.
    reach = math.sqrt(float(np.max(px * px + py * py))) if n else 0.0
    current = -1.0
    at: tuple[FloatArray, FloatArray, FloatArray] | None = None  # corners, fu, fv at (x, y, th)
    for _ in range(iterations):
        c, s = math.cos(th), math.sin(th)
        if at is None:
            at = _corners_at(field, px, py, ((x, y, th),), origin, res, reach)
        (m00, m10, m01, m11), fu, fv = at
        fu, fv = fu[0], fv[0]
        m00, m10, m01, m11 = m00[0], m10[0], m01[0], m11[0]
        gu, gv = 1 - fu, 1 - fv
        val = gv * (gu * m00 + fu * m10) + fv * (gu * m01 + fu * m11)
        du = gv * (m10 - m00) + fv * (m11 - m01)
        dv = gu * (m01 - m00) + fu * (m11 - m10)
        if current < 0.0:
            current = float(np.add.reduce(val)) / n
        gx, gy = du / res, dv / res  # per metre
        dwx_dth = -s * px - c * py
        dwy_dth = c * px - s * py
        jac = np.empty((n, 3))  # (N, 3), C order: np.column_stack's layout, without its overhead
        jac[:, 0], jac[:, 1], jac[:, 2] = gx, gy, gx * dwx_dth + gy * dwy_dth
        hess = jac.T @ jac
        grad = jac.T @ (1.0 - val)
        h00, h11, h22 = float(hess[0, 0]), float(hess[1, 1]), float(hess[2, 2])
        if not math.isfinite(float(np.add.reduce(hess, axis=None))) or (h00 + h11) + h22 < 1e-9:
            break
        # Levenberg damping (np.diag(np.maximum(np.diag(hess), 1e-6) * 0.1 + 1e-6), in floats)
        hess[0, 0] = h00 + (max(h00, 1e-6) * 0.1 + 1e-6)
        hess[1, 1] = h11 + (max(h11, 1e-6) * 0.1 + 1e-6)
        hess[2, 2] = h22 + (max(h22, 1e-6) * 0.1 + 1e-6)
        step = _solve(hess, grad)
        if step is None:
            break
        # Bound the step: the linearisation holds within about a cell. Then up to 4 halvings of it.
        s0, s1, s2 = (float(v) for v in step)
        bound = max(1.0, math.hypot(s0, s1) / res, abs(s2) / math.radians(1.0))
        s0, s1, s2 = s0 / bound, s1 / bound, s2 / bound
        cands = []
        for _half in range(4):
            cands.append((x + s0, y + s1, th + s2))
            s0, s1, s2 = s0 / 2.0, s1 / 2.0, s2 / 2.0
        corners, cu, cv = _corners_at(field, px, py, cands, origin, res, reach)
        scores = np.add.reduce(_blend(corners, cu, cv), axis=1) / n
        better = np.flatnonzero(scores > current)
        if not better.size:
            break  # no step along this direction helps: at the optimum
        k = int(better[0])
        x, y, th = cands[k]
        score = float(scores[k])
        at = (corners[:, k : k + 1], cu[k : k + 1], cv[k : k + 1])
        gain, current = score - current, score
        if gain < 1e-5:
            break
    return (x, y, th), current


def _solve(a: FloatArray, b: FloatArray) -> FloatArray | None:
    """``np.linalg.solve(a, b)`` for one small system; None where it raises (singular). (scipy's
    ``lapack.dgesv`` is the same routine without numpy's wrapping and a few microseconds cheaper,
    but importing scipy.linalg costs every agent process ~29 MB of RSS: bench/scale.py's agents
    went from 72 to 101 MB, over the 80 MB goal.)"""
    try:
        out: FloatArray = np.linalg.solve(a, b).astype(np.float64, copy=False)
    except np.linalg.LinAlgError:
        return None
    return out


def _solve_each(a: FloatArray, b: FloatArray, active: npt.NDArray[np.bool_]) -> FloatArray:
    """``_solve`` of each (3, 3) system ``a[k] x = b[k]`` that is ``active``, at once (0 for the rest);
    a singular one, as ``_solve`` finds it alone, is made inactive instead (its solution 0)."""
    out = np.zeros(b.shape)
    act = np.flatnonzero(active)
    try:
        out[act] = np.linalg.solve(a[act], b[act, :, None])[:, :, 0]
    except np.linalg.LinAlgError:  # one of them singular: each alone
        for k in act.tolist():
            sol = _solve(a[k], b[k])
            if sol is None:
                active[k] = False
            else:
                out[k] = sol
    return out


def _corners_at(
    field: npt.NDArray[np.float32],
    px: FloatArray,
    py: FloatArray,
    poses: Sequence[Pose],
    origin: tuple[float, float],
    res: float,
    reach: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``_corners`` of the points seen from each of ``poses``: ((4, P, N), (P, N), (P, N)). Each element
    computed as ``_score_at`` computes it for one pose."""
    cs = np.array([(p[0], p[1], math.cos(p[2]), math.sin(p[2])) for p in poses])
    x, y, c, s = cs[:, 0:1], cs[:, 1:2], cs[:, 2:3], cs[:, 3:4]
    u = (x + c * px - s * py - origin[0]) / res - 0.5
    v = (y + s * px + c * py - origin[1]) / res - 0.5
    shape = (int(field.shape[0]), int(field.shape[1]))
    inside = all(_inside(shape, reach, p[0], p[1], origin, res) for p in poses)
    return _corners(field, u, v, inside)


def _blend(m: FloatArray, fu: FloatArray, fv: FloatArray) -> FloatArray:
    """Bilinear interpolation of the corners ``m`` (as ``_interp``)."""
    gu = 1 - fu
    out: FloatArray = (1 - fv) * (gu * m[0] + fu * m[1]) + fv * (gu * m[2] + fu * m[3])
    return out


# -- point-to-line refinement against a local map of recent keyframes ------------------------------

_KEY_OFFSET = 1 << 30
_NX = np.repeat(np.arange(-1, 2, dtype=np.int64), 3)  # the 3x3 neighbourhood of a cell
_NY = np.tile(np.arange(-1, 2, dtype=np.int64), 3)


def _keys(kx: npt.NDArray[np.int64], ky: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    out: npt.NDArray[np.int64] = (kx + _KEY_OFFSET) * (1 << 32) + (ky + _KEY_OFFSET)
    return out


def scan_normals(points: FloatArray, labels: npt.NDArray[np.int64], reach: int = 2) -> FloatArray:
    """Unit normal per point (sensor frame, facing the sensor) from its neighbours along the scan within
    its segment (``reach`` either side); NaN where a point has no neighbour in its segment."""
    n = len(points)
    out = np.full((n, 2), np.nan)
    if n < 2:
        return out
    idx = np.arange(n)
    lo = idx.copy()
    hi = idx.copy()
    for k in range(1, reach + 1):
        a = np.maximum(idx - k, 0)
        b = np.minimum(idx + k, n - 1)
        lo = np.where(labels[a] == labels, a, lo)
        hi = np.where(labels[b] == labels, b, hi)
    d = points[hi] - points[lo]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = (hi > lo) & (length > 1e-6)
    nx, ny = -d[:, 1], d[:, 0]
    flip = nx * points[:, 0] + ny * points[:, 1] > 0  # face the sensor (the origin)
    nx = np.where(flip, -nx, nx)
    ny = np.where(flip, -ny, ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        out[ok, 0] = nx[ok] / length[ok]
        out[ok, 1] = ny[ok] / length[ok]
    return out


class LocalMap:
    """The points and normals of the last ``keyframes`` integrated scans, in the map frame, fused per
    ``cell`` (mean point, mean normal): the reference for point-to-line refinement. Matching against
    recent keyframes instead of the whole grid keeps the accumulated grid's blur and older errors out of
    the fine alignment."""

    def __init__(self, keyframes: int = 5, cell: float = 0.1) -> None:
        if keyframes < 1 or cell <= 0:
            raise ValueError("need keyframes >= 1 and cell > 0")
        self.keyframes = keyframes
        self.cell = cell
        self._frames: list[tuple[FloatArray, FloatArray]] = []
        self.keys: npt.NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        self.points: FloatArray = np.zeros((0, 2))
        self.normals: FloatArray = np.zeros((0, 2))
        self._table: npt.NDArray[np.intp] = np.full(1, -1, dtype=np.intp)
        self._tx0 = self._ty0 = self._tw = self._th = 0
        self._noff: npt.NDArray[np.int64] = np.zeros(9, dtype=np.int64)
        self._px: FloatArray = np.zeros(1)
        self._py: FloatArray = np.zeros(1)
        self.stacked: FloatArray = np.zeros((4, 0))

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, sensor_pose: Pose, points: FloatArray, normals: FloatArray) -> None:
        """Add one keyframe's points and normals (sensor frame) seen from ``sensor_pose``."""
        self.extend([(sensor_pose, points, normals)])

    def extend(self, frames: Sequence[tuple[Pose, FloatArray, FloatArray]]) -> None:
        """``add`` each of ``frames`` (sensor pose, points, normals) in order, the points fused once at the
        end: the same map as adding them one by one."""
        for sensor_pose, points, normals in frames:
            ok = np.isfinite(normals).all(axis=1)
            c, s = math.cos(sensor_pose[2]), math.sin(sensor_pose[2])
            wp = _transform(points[ok], *sensor_pose)
            nv = normals[ok]
            wn = np.column_stack((c * nv[:, 0] - s * nv[:, 1], s * nv[:, 0] + c * nv[:, 1]))
            self._frames.append((wp, wn))
        del self._frames[: -self.keyframes]
        if not self._frames:
            return
        pts = np.vstack([f[0] for f in self._frames])
        nrm = np.vstack([f[1] for f in self._frames])
        k = np.floor(pts / self.cell).astype(np.int64)
        keys, inv = np.unique(_keys(k[:, 0], k[:, 1]), return_inverse=True)
        inv = inv.ravel()
        cnt = np.bincount(inv).astype(np.float64)
        mean = np.column_stack([np.bincount(inv, pts[:, i]) / cnt for i in (0, 1)])
        nsum = np.column_stack([np.bincount(inv, nrm[:, i]) for i in (0, 1)])
        nlen = np.hypot(nsum[:, 0], nsum[:, 1])
        good = nlen > 0.5 * cnt  # normals that agree (a thin wall seen from both sides cancels out)
        self.keys = keys[good]
        self.points = mean[good]
        self.normals = nsum[good] / nlen[good, None]
        self._build_table()

    def _build_table(self) -> None:
        """A dense table over the fused points' cells: per cell, the index of its fused point (-1: none).
        ``nearest`` then reads the 3x3 cells around a point with one gather instead of nine sorted-key
        searches; built once per keyframe added. Three empty cells pad each side: a query cell more than
        one cell outside the points' box reads the all-empty cell next to the corner instead."""
        n = len(self.keys)
        if n == 0:
            self._table = np.full(1, -1, dtype=np.intp)
            self._tx0 = self._ty0 = self._tw = self._th = 0
            return
        cx = (self.keys >> 32) - _KEY_OFFSET
        cy = (self.keys & 0xFFFFFFFF) - _KEY_OFFSET
        self._tx0, self._ty0 = int(cx.min()) - 3, int(cy.min()) - 3
        self._tw, self._th = int(cx.max()) - self._tx0 + 4, int(cy.max()) - self._ty0 + 4
        table = np.full(self._tw * self._th, -1, dtype=np.intp)
        table[(cy - self._ty0) * self._tw + (cx - self._tx0)] = np.arange(n, dtype=np.intp)
        self._table = table
        self._noff = _NY * self._tw + _NX  # the 3x3 neighbours' flat offsets, in _NX/_NY order
        # Gathers read these; index -1 (none) reads the appended point at infinity.
        self._px = np.append(self.points[:, 0], np.inf)
        self._py = np.append(self.points[:, 1], np.inf)
        # Rows x, y, normal x, normal y: one gather per iteration of ``icp_refine`` instead of four.
        self.stacked = np.vstack((self.points.T, self.normals.T))

    def nearest(self, xy: FloatArray) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """Index of the nearest fused point within the 3x3 cells around each of ``xy`` (-1: none), and
        its distance."""
        return self.nearest_xy(xy[:, 0], xy[:, 1])

    def nearest_xy(self, x: FloatArray, y: FloatArray) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """``nearest`` on separate coordinate arrays."""
        n = len(x)
        if n == 0 or len(self.keys) == 0:
            return np.full(n, -1, dtype=np.int64), np.full(n, np.inf)
        return self._pick(self._gather(self._cells(x, y)), x, y)

    def _cells(self, x: FloatArray, y: FloatArray) -> npt.NDArray[np.int64]:
        """The table cell of each point (one all-empty cell for points more than a cell outside)."""
        ix = np.floor(x / self.cell).astype(np.int64) - self._tx0
        iy = np.floor(y / self.cell).astype(np.int64) - self._ty0
        inside = (ix >= 2) & (ix < self._tw - 2) & (iy >= 2) & (iy < self._th - 2)
        cells: npt.NDArray[np.int64] = np.where(inside, iy * self._tw + ix, self._tw + 1)
        return cells

    def _gather(self, cells: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.intp], FloatArray, FloatArray]:
        """The fused points in the 3 x 3 cells around each of ``cells``: (N, 9) indices (-1: none) and
        their coordinates (inf: none)."""
        i = self._table[cells[:, None] + self._noff[None, :]]
        return i, self._px[i], self._py[i]

    def _pick(
        self, near: tuple[npt.NDArray[np.intp], FloatArray, FloatArray], x: FloatArray, y: FloatArray
    ) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """The nearest of ``near`` (``_gather``'s) to each point, and its distance."""
        i, gx, gy = near
        # The nearest by squared distance (cheaper than hypot over all nine), its distance by hypot.
        dx = gx - x[:, None]  # none: inf
        dy = gy - y[:, None]
        dx *= dx
        dy *= dy
        dx += dy
        rows = np.arange(len(x))
        j = dx.argmin(axis=1)
        best = i[rows, j]  # -1 where all nine are empty (their distance: inf)
        dist = np.hypot(self._px[best] - x, self._py[best] - y)
        return best.astype(np.int64), dist


@dataclass(frozen=True, slots=True)
class IcpResult:
    pose: Pose
    inliers: int  # correspondences used at the last iteration
    weak: float  # smallest eigenvalue of the data information (1/m^2 units, theta scaled by 1 m)
    information: FloatArray | None = None  # the data's information on (x, y, theta) at the answer (None: no data)


def icp_refine(
    local: LocalMap,
    points: FloatArray,
    pose: Pose,
    prior_pose: Pose,
    prior: tuple[float, float],
    sigma: float = 0.03,
    max_distance: float = 0.15,
    iterations: int = 8,
    tolerance: float = 1e-4,
) -> IcpResult:
    """Point-to-line Gauss-Newton of ``points`` (sensor frame) against ``local`` from ``pose``, with a
    Gaussian prior at ``prior_pose`` ((sd xy, sd theta)). Correspondences (nearest fused point within
    ``max_distance``) are found again at every iteration; residuals are Cauchy-weighted (scale
    ``sigma``). Along a direction the points do not constrain (a corridor) the data information is ~0
    and the prior holds the pose there: the fallback to odometry happens per direction. Stops once a
    step moves less than ``tolerance`` (m, and rad)."""
    x, y, th = pose
    px, py = points[:, 0], points[:, 1]
    sxy, sth = max(prior[0], 1e-3), max(prior[1], 1e-4)
    lam = np.diag([1.0 / sxy**2, 1.0 / sxy**2, 1.0 / sth**2])
    inliers = 0
    hd_last: FloatArray | None = None
    # Rows: the points in the map frame (x, y; rewritten each iteration), in the sensor frame (x, y): the
    # inliers are then picked out of all four at once, and the local map's points and normals likewise.
    pts = np.empty((4, len(px)))
    pts[2], pts[3] = px, py
    wx, wy = pts[0], pts[1]
    if len(local) == 0 or len(px) == 0:
        return IcpResult((x, y, th), 0, 0.0, None)
    near: tuple[npt.NDArray[np.intp], FloatArray, FloatArray] | None = None
    last_cells: npt.NDArray[np.int64] | None = None
    for _ in range(iterations):
        c, s = math.cos(th), math.sin(th)
        np.multiply(px, c, out=wx)  # x + c px - s py, in that order
        wx += x
        wx -= s * py
        np.multiply(px, s, out=wy)  # y + s px + c py
        wy += y
        wy += c * py
        # Correspondences: the 3 x 3 cells' fused points gathered again only for the points whose
        # cell changed since the last iteration (most keep theirs: the steps are millimetres).
        cells = local._cells(wx, wy)
        if near is None or last_cells is None:
            near = local._gather(cells)
        else:
            moved = np.flatnonzero(cells != last_cells)
            if moved.size:
                fresh = local._gather(cells[moved])
                for old_part, new_part in zip(near, fresh, strict=True):
                    old_part[moved] = new_part
        last_cells = cells
        idx, dist = local._pick(near, wx, wy)
        ok = dist <= max_distance  # none: inf
        inliers = int(np.count_nonzero(ok))
        if inliers < 3:
            break
        wxo, wyo, pxo, pyo = pts.compress(ok, axis=1)
        lpx, lpy, nx, ny = local.stacked.take(idx[ok], axis=1)
        r = nx * (wxo - lpx) + ny * (wyo - lpy)
        w = 1.0 / (1.0 + (r / sigma) ** 2) / sigma**2
        dth = nx * (-s * pxo - c * pyo) + ny * (c * pxo - s * pyo)
        jac = np.empty((len(nx), 3))  # (K, 3), C order: np.column_stack's layout, without its overhead
        jac[:, 0], jac[:, 1], jac[:, 2] = nx, ny, dth
        jw = (jac * w[:, None]).T
        hd = jw @ jac
        dev = np.array([x - prior_pose[0], y - prior_pose[1], math.remainder(th - prior_pose[2], 2.0 * math.pi)])
        hess = hd + lam
        grad = jw @ r + lam @ dev
        sol = _solve(hess, grad)
        if sol is None:
            break
        step = -sol
        x, y, th = x + float(step[0]), y + float(step[1]), th + float(step[2])
        hd_last = hd
        if math.hypot(step[0], step[1]) < tolerance and abs(step[2]) < tolerance:
            break
    weak = 0.0 if hd_last is None else float(np.linalg.eigvalsh(hd_last)[0])
    return IcpResult((x, y, th), inliers, weak, hd_last)


# Points per batch of ``icp_refine_many``: its (points x 9) neighbour arrays stay near 13 MB each. The
# references' cell tables are joined per batch besides (mit-csail's final pass: up to 89 of them, 26 MB).
_MANY_POINTS = 60_000


def icp_refine_many(
    tasks: Sequence[tuple[LocalMap, FloatArray, Pose]],
    prior: tuple[float, float],
    sigma: float = 0.03,
    max_distance: float = 0.15,
    iterations: int = 8,
    tolerance: float = 1e-4,
) -> list[IcpResult]:
    """``icp_refine`` of each (reference, points, start) of ``tasks``, the prior at its start: the same
    iterations, correspondences, weights, steps and stops, task by task, computed for all tasks at once.
    A replay's final pass refines thousands of small independent pairs (150 points, 10 iterations);
    one at a time, numpy's per-call cost is most of it. The sums over each task's points are taken in
    another order than ``icp_refine`` takes them, so an answer may differ from it in the last bits."""
    out: list[IcpResult | None] = [None] * len(tasks)
    live = []
    for t, (local, points, start) in enumerate(tasks):
        if len(local) == 0 or len(points) == 0:
            out[t] = IcpResult(start, 0, 0.0, None)
        else:
            live.append(t)
    batch: list[int] = []
    size = 0
    for t in live:
        batch.append(t)
        size += len(tasks[t][1])
        if size >= _MANY_POINTS:
            _refine_batch(tasks, batch, out, prior, sigma, max_distance, iterations, tolerance)
            batch, size = [], 0
    if batch:
        _refine_batch(tasks, batch, out, prior, sigma, max_distance, iterations, tolerance)
    return [r for r in out if r is not None]


def _refine_batch(
    tasks: Sequence[tuple[LocalMap, FloatArray, Pose]],
    batch: list[int],
    out: list[IcpResult | None],
    prior: tuple[float, float],
    sigma: float,
    max_distance: float,
    iterations: int,
    tolerance: float,
) -> None:
    """``icp_refine_many`` of the tasks ``batch`` (each with points and a reference), into ``out``."""
    # The references' tables and points joined into one: a task's cell indexes its reference's part of
    # the table, and every "none" reads one point at infinity after all the references' points.
    ref_of: dict[int, int] = {}
    refs: list[LocalMap] = []
    for t in batch:
        if id(tasks[t][0]) not in ref_of:
            ref_of[id(tasks[t][0])] = len(refs)
            refs.append(tasks[t][0])
    p_off = np.cumsum([0] + [len(r) for r in refs])
    none = int(p_off[-1])
    t_off = np.cumsum([0] + [len(r._table) for r in refs])
    table = np.concatenate([np.where(r._table >= 0, r._table + p_off[i], none) for i, r in enumerate(refs)])
    gx_all = np.concatenate([r.points[:, 0] for r in refs] + [np.array([np.inf])])
    gy_all = np.concatenate([r.points[:, 1] for r in refs] + [np.array([np.inf])])
    stacked = np.hstack([r.stacked for r in refs] + [np.zeros((4, 1))])
    ri = np.array([ref_of[id(tasks[t][0])] for t in batch])
    cell = np.array([r.cell for r in refs])[ri]
    tx0 = np.array([r._tx0 for r in refs], dtype=np.int64)[ri]
    ty0 = np.array([r._ty0 for r in refs], dtype=np.int64)[ri]
    tw = np.array([r._tw for r in refs], dtype=np.int64)[ri]
    th_ = np.array([r._th for r in refs], dtype=np.int64)[ri]
    toff = t_off[:-1][ri]
    noff = _NY[None, :] * tw[:, None] + _NX[None, :]  # (T, 9)
    counts = np.array([len(tasks[t][1]) for t in batch])
    pts = np.vstack([tasks[t][1] for t in batch])
    start = np.array([tasks[t][2] for t in batch], dtype=np.float64)
    pose = start.copy()
    lam = np.array([1.0 / max(prior[0], 1e-3) ** 2] * 2 + [1.0 / max(prior[1], 1e-4) ** 2])
    inliers = np.zeros(len(batch), dtype=np.int64)
    hd_last = np.zeros((len(batch), 3, 3))
    has_hd = np.zeros(len(batch), dtype=bool)
    active = np.ones(len(batch), dtype=bool)
    # The points of the tasks still refining (dropped in bulk as tasks stop): each one's task, its
    # sensor-frame coordinates, its cell and the 3 x 3 cells' fused points (their index and coordinates,
    # gathered again only where the cell changed: most keep theirs, the steps are millimetres).
    tp = np.repeat(np.arange(len(batch)), counts)
    px, py = pts[:, 0].copy(), pts[:, 1].copy()
    last = np.full(len(tp), -1, dtype=np.int64)
    near = np.empty((len(tp), 9), dtype=np.intp)
    gx, gy = np.empty((len(tp), 9)), np.empty((len(tp), 9))
    for _ in range(iterations):
        if np.count_nonzero(active[tp]) < 0.75 * len(tp):
            keep = active[tp]
            tp, last, near = tp[keep], last[keep], near[keep]
            px, py, gx, gy = px[keep], py[keep], gx[keep], gy[keep]
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        cp, sp = c[tp], s[tp]
        wx = px * cp + pose[tp, 0] - sp * py  # as icp_refine: x + c px - s py
        wy = px * sp + pose[tp, 1] + cp * py
        ix = np.floor(wx / cell[tp]).astype(np.int64) - tx0[tp]
        iy = np.floor(wy / cell[tp]).astype(np.int64) - ty0[tp]
        inside = (ix >= 2) & (ix < tw[tp] - 2) & (iy >= 2) & (iy < th_[tp] - 2)
        cells = np.where(inside, iy * tw[tp] + ix, tw[tp] + 1) + toff[tp]
        moved = np.flatnonzero(cells != last)
        if moved.size:
            i = table[cells[moved, None] + noff[tp[moved]]]
            near[moved], gx[moved], gy[moved] = i, gx_all[i], gy_all[i]
            last = cells
        dx = gx - wx[:, None]
        dy = gy - wy[:, None]
        dx *= dx
        dy *= dy
        dx += dy
        best = near[np.arange(len(tp)), dx.argmin(axis=1)]
        dist = np.hypot(gx_all[best] - wx, gy_all[best] - wy)
        ok = dist <= max_distance
        n_ok = np.bincount(tp[ok], minlength=len(batch))
        inliers[active] = n_ok[active]
        active &= n_ok >= 3
        if not active.any():
            break
        use = ok & active[tp]
        to = tp[use]
        lpx, lpy, nx, ny = stacked[:, best[use]]
        wxo, wyo, pxo, pyo = wx[use], wy[use], px[use], py[use]
        r = nx * (wxo - lpx) + ny * (wyo - lpy)
        w = 1.0 / (1.0 + (r / sigma) ** 2) / sigma**2
        co, so = c[to], s[to]
        dth = nx * (-so * pxo - co * pyo) + ny * (co * pxo - so * pyo)
        n = len(batch)
        wnx, wny, wdth = w * nx, w * ny, w * dth
        hd = np.empty((n, 3, 3))
        hd[:, 0, 0] = np.bincount(to, wnx * nx, n)
        hd[:, 0, 1] = hd[:, 1, 0] = np.bincount(to, wnx * ny, n)
        hd[:, 0, 2] = hd[:, 2, 0] = np.bincount(to, wnx * dth, n)
        hd[:, 1, 1] = np.bincount(to, wny * ny, n)
        hd[:, 1, 2] = hd[:, 2, 1] = np.bincount(to, wny * dth, n)
        hd[:, 2, 2] = np.bincount(to, wdth * dth, n)
        grad: FloatArray = np.column_stack([np.bincount(to, v * r, n) for v in (wnx, wny, wdth)])
        dev = pose - start
        dev[:, 2] -= 2.0 * math.pi * np.round(dev[:, 2] / (2.0 * math.pi))
        grad += lam * dev
        hess = hd + np.diag(lam)
        step = -_solve_each(hess, grad, active)
        pose[active] += step[active]
        hd_last[active] = hd[active]
        has_hd |= active
        done = active & (np.hypot(step[:, 0], step[:, 1]) < tolerance) & (np.abs(step[:, 2]) < tolerance)
        active &= ~done
        if not active.any():
            break
    weak = np.zeros(len(batch))
    if has_hd.any():
        weak[has_hd] = np.linalg.eigvalsh(hd_last[has_hd])[:, 0]
    for k, t in enumerate(batch):
        info = hd_last[k].copy() if has_hd[k] else None
        p = (float(pose[k, 0]), float(pose[k, 1]), float(pose[k, 2]))
        out[t] = IcpResult(p, int(inliers[k]), float(weak[k]), info)


def _refine_many(
    grid: FieldMap, tasks: Sequence[tuple[FloatArray, Pose]], iterations: int = 8
) -> list[tuple[Pose, float]]:
    """``_refine`` of each (points, pose) of ``tasks`` on one field, all at once: the same steps,
    halvings and stops task by task, its sums over each task's points taken in another order (so an
    answer may differ from ``_refine``'s in the last bits). A task with no points keeps its pose
    (score -1)."""
    res, origin, field = grid.resolution, grid.origin, grid.field
    out: list[tuple[Pose, float]] = [(p, -1.0) for _, p in tasks]
    live = [t for t, (pts, _) in enumerate(tasks) if len(pts)]
    if not live:
        return out
    n_t = len(live)
    counts = np.array([len(tasks[t][0]) for t in live])
    tp = np.repeat(np.arange(n_t), counts)
    pts = np.vstack([tasks[t][0] for t in live])
    px, py = pts[:, 0], pts[:, 1]
    n = counts.astype(np.float64)
    pose = np.array([tasks[t][1] for t in live], dtype=np.float64)
    current = np.full(n_t, -1.0)
    active = np.ones(n_t, dtype=bool)

    def trig(th: FloatArray) -> tuple[FloatArray, FloatArray]:
        return np.array([math.cos(a) for a in th]), np.array([math.sin(a) for a in th])

    def corners(at: FloatArray, which: npt.NDArray[np.intp]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``_corners`` of the points ``which``, each seen from its task's pose in ``at``."""
        c, s = trig(at[:, 2])
        q, x, y = tp[which], px[which], py[which]
        u = (at[q, 0] + c[q] * x - s[q] * y - origin[0]) / res - 0.5
        v = (at[q, 1] + s[q] * x + c[q] * y - origin[1]) / res - 0.5
        return _corners(field, u, v)

    every = np.arange(len(tp))
    for _ in range(iterations):
        c, s = trig(pose[:, 2])
        (m00, m10, m01, m11), fu, fv = corners(pose, every)
        gu, gv = 1 - fu, 1 - fv
        val = gv * (gu * m00 + fu * m10) + fv * (gu * m01 + fu * m11)
        du = gv * (m10 - m00) + fv * (m11 - m01)
        dv = gu * (m01 - m00) + fu * (m11 - m10)
        first = current < 0.0
        current[first] = (np.bincount(tp, val, n_t) / n)[first]
        gx, gy = du / res, dv / res
        j2 = gx * (-s[tp] * px - c[tp] * py) + gy * (c[tp] * px - s[tp] * py)
        hess = np.empty((n_t, 3, 3))
        cols = (gx, gy, j2)
        for a in range(3):
            for b in range(a, 3):
                hess[:, a, b] = hess[:, b, a] = np.bincount(tp, cols[a] * cols[b], n_t)
        e = 1.0 - val
        grad: FloatArray = np.column_stack([np.bincount(tp, col * e, n_t) for col in cols])
        diag = hess[:, [0, 1, 2], [0, 1, 2]]
        active &= np.isfinite(hess.sum(axis=(1, 2))) & (diag.sum(axis=1) >= 1e-9)
        if not active.any():
            break
        hess[:, [0, 1, 2], [0, 1, 2]] = diag + (np.maximum(diag, 1e-6) * 0.1 + 1e-6)
        step = _solve_each(hess, grad, active)
        bound = np.maximum(
            1.0, np.maximum(np.hypot(step[:, 0], step[:, 1]) / res, np.abs(step[:, 2]) / math.radians(1.0))
        )
        step /= bound[:, None]
        # Four halvings of each step, each scored for every task still refining (the rest: never taken).
        scores = np.empty((n_t, 4))
        cand = np.empty((n_t, 4, 3))
        sel = np.flatnonzero(active[tp])
        for h_ in range(4):
            cand[:, h_] = pose + step / (2.0**h_)
            scores[:, h_] = np.bincount(tp[sel], _blend(*corners(cand[:, h_], sel)), n_t) / n
        better = scores > current[:, None]
        moved = active & better.any(axis=1)
        k = better.argmax(axis=1)
        active &= moved  # no step along this direction helps: at the optimum
        idx = np.flatnonzero(moved)
        new_score = scores[idx, k[idx]]
        gain = new_score - current[idx]
        pose[idx] = cand[idx, k[idx]]
        current[idx] = new_score
        active[idx[gain < 1e-5]] = False
        if not active.any():
            break
    for i, t in enumerate(live):
        out[t] = ((float(pose[i, 0]), float(pose[i, 1]), float(pose[i, 2])), float(current[i]))
    return out
