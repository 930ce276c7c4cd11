"""Multilateration: a 2D tag position (known tag height) from ranges to known anchors.

``solve`` is the fix the gateway publishes: weighted nonlinear least squares on the 3D range
residuals, Gauss-Newton with a step-halving line search, iteratively reweighted by a robust loss
(a Huber stage for a safe start, then Cauchy so gross outliers and NLOS biases lose their pull).
``solve_linear`` is the textbook baseline the benchmark compares against: subtract the mean range
equation to make the problem linear and solve it by ordinary least squares (no robustness, and
the squaring amplifies the error of far ranges).

Both refuse rather than guess: fewer than 3 usable ranges -> ``TOO_FEW_RANGES``; anchors (nearly)
on one line -> ``DEGENERATE_GEOMETRY`` (the mirror image of the tag fits as well); no convergence
or a position far from every anchor -> ``DIVERGED``. A refused solution has NaN x, y, infinite
sd and quality 0.

Unknowns are two, so the normal equations are 2x2 and solved in closed form: plain Python floats
keep a solve at tens of microseconds, far below what numpy's per-call overhead would cost for ten
anchors. Pure: no I/O, no clock.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from fleetlink.shared.messages import FixStatus

from .anchors import Anchor

__all__ = ["FixStatus", "Loss", "Solution", "quality_from_sd", "solve", "solve_linear"]

DEFAULT_SIGMA_M = 0.1
HUBER_K = 1.345  # x sigma: 95 % efficiency on Gaussian noise
CAUCHY_K = 2.385  # x sigma: 95 % efficiency on Gaussian noise
MIN_SPREAD_M = 0.3  # anchors' spread across their best-fit line below this: collinear
MIN_SPREAD_RATIO = 0.03  # ... or below this fraction of the spread along it
MAX_ITERATIONS = 30
STEP_TOL_M = 1e-3  # 1 mm: far below the fix noise
MAX_COND = 1e8  # condition number of the normal matrix beyond which the fix is meaningless
INLIER_WEIGHT = 0.5


class Loss(enum.StrEnum):
    L2 = "l2"
    HUBER = "huber"
    CAUCHY = "cauchy"


@dataclass(frozen=True, slots=True)
class Solution:
    """One fix. ``used``: anchors whose ranges counted (robust weight >= 0.5) in input order."""

    status: FixStatus
    x: float
    y: float
    z: float
    sd_x: float
    sd_y: float
    quality: int
    residual_rms_m: float
    used: tuple[str, ...]
    iterations: int = 0

    @property
    def ok(self) -> bool:
        return self.status is FixStatus.OK


_Rows = list[tuple[float, float, float, float, str]]  # anchor x, y, dz^2, measured range, id


def _refused(status: FixStatus, z: float, used: tuple[str, ...] = ()) -> Solution:
    nan, inf = math.nan, math.inf
    return Solution(status, nan, nan, z, inf, inf, 0, nan, used)


def _rows(anchors: Sequence[Anchor] | Mapping[str, Anchor], ranges: Iterable[Any], tag_z: float) -> _Rows:
    """Usable ranges: known anchor, finite, >= 0, first one per anchor."""
    by_id = anchors if isinstance(anchors, Mapping) else {a.id: a for a in anchors}
    rows: _Rows = []
    seen: set[str] = set()
    for r in ranges:
        if isinstance(r, tuple):
            aid, m = r[0], r[1]
        else:
            aid = getattr(r, "anchor_id", None)
            if aid is None:
                aid = r.anchor
            m = r.distance_m
        a = by_id.get(aid)
        if a is None or aid in seen or not (isinstance(m, (int, float)) and math.isfinite(m) and m >= 0):
            continue
        seen.add(aid)
        dz = tag_z - a.z
        rows.append((a.x, a.y, dz * dz, float(m), aid))
    return rows


def _collinear(rows: _Rows) -> bool:
    n = len(rows)
    mx = sum(r[0] for r in rows) / n
    my = sum(r[1] for r in rows) / n
    sxx = sum((r[0] - mx) ** 2 for r in rows) / n
    syy = sum((r[1] - my) ** 2 for r in rows) / n
    sxy = sum((r[0] - mx) * (r[1] - my) for r in rows) / n
    half_tr = 0.5 * (sxx + syy)
    disc = math.sqrt(max(0.0, half_tr * half_tr - (sxx * syy - sxy * sxy)))
    across = math.sqrt(max(0.0, half_tr - disc))  # sd of the anchors across their best-fit line
    along = math.sqrt(half_tr + disc)
    return across < MIN_SPREAD_M or across < MIN_SPREAD_RATIO * along


def _linear(rows: _Rows) -> tuple[float, float] | None:
    """Mean-subtracted linearisation: -2 a_i . p + |p|^2 = h_i^2 - |a_i|^2, minus its mean."""
    n = len(rows)
    mx = sum(r[0] for r in rows) / n
    my = sum(r[1] for r in rows) / n
    ks = [r[3] * r[3] - r[2] - r[0] * r[0] - r[1] * r[1] for r in rows]
    mk = sum(ks) / n
    a11 = a12 = a22 = b1 = b2 = 0.0
    for (ax, ay, _dz2, _m, _id), k in zip(rows, ks, strict=True):
        ux, uy, v = -2.0 * (ax - mx), -2.0 * (ay - my), k - mk
        a11 += ux * ux
        a12 += ux * uy
        a22 += uy * uy
        b1 += ux * v
        b2 += uy * v
    det = a11 * a22 - a12 * a12
    if det <= 1e-12 * max(1.0, a11 * a22):
        return None
    return (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det


def _weight(loss: Loss, r: float, c: float) -> float:
    if loss is Loss.CAUCHY:
        t = r / c
        return 1.0 / (1.0 + t * t)
    if loss is Loss.HUBER:
        a = abs(r)
        return 1.0 if a <= c else c / a
    return 1.0


def _cost(loss: Loss, rows: _Rows, x: float, y: float, c: float) -> float:
    total = 0.0
    sqrt, log1p = math.sqrt, math.log1p
    for ax, ay, dz2, m, _ in rows:
        dx, dy = x - ax, y - ay
        r = sqrt(dx * dx + dy * dy + dz2) - m
        if loss is Loss.CAUCHY:
            total += log1p((r / c) ** 2)
        elif loss is Loss.HUBER:
            a = abs(r)
            total += r * r if a <= c else c * (2.0 * a - c)
        else:
            total += r * r
    return total


def _gauss_newton(
    rows: _Rows, x: float, y: float, loss: Loss, c: float, max_iter: int
) -> tuple[float, float, int, bool]:
    """IRLS Gauss-Newton from (x, y); returns (x, y, iterations, converged)."""
    sqrt = math.sqrt
    cost = _cost(loss, rows, x, y, c)
    for it in range(1, max_iter + 1):
        a11 = a12 = a22 = b1 = b2 = 0.0
        for ax, ay, dz2, m, _ in rows:
            dx, dy = x - ax, y - ay
            rho = sqrt(dx * dx + dy * dy + dz2)
            if rho < 1e-9:
                continue
            r = rho - m
            w = _weight(loss, r, c)
            jx, jy = dx / rho, dy / rho
            wjx, wjy = w * jx, w * jy
            a11 += wjx * jx
            a12 += wjx * jy
            a22 += wjy * jy
            b1 += wjx * r
            b2 += wjy * r
        det = a11 * a22 - a12 * a12
        if not det > 1e-18:
            return x, y, it, False
        sx = -(a22 * b1 - a12 * b2) / det
        sy = -(a11 * b2 - a12 * b1) / det
        # Step halving on the robust cost keeps IRLS from overshooting when weights change.
        step = 1.0
        for _ in range(8):
            nx, ny = x + step * sx, y + step * sy
            new_cost = _cost(loss, rows, nx, ny, c)
            if new_cost <= cost:
                break
            step *= 0.5
        else:
            return x, y, it, True  # no descent along the step: at a minimum within tolerance
        x, y, cost = nx, ny, new_cost
        if step * math.hypot(sx, sy) < STEP_TOL_M:
            return x, y, it, True
    return x, y, max_iter, False


def quality_from_sd(sd_x: float, sd_y: float, inlier_share: float = 1.0) -> int:
    """PANS-style quality 0-100: 100 while the per-axis sd is <= 0.1 m, then 100 * 0.1 / sd,
    scaled by the share of ranges the fix trusted."""
    sd = math.sqrt(0.5 * (sd_x * sd_x + sd_y * sd_y))
    if not math.isfinite(sd):
        return 0
    q = 100.0 * min(1.0, 0.1 / max(sd, 1e-9)) * min(1.0, max(0.0, inlier_share))
    return max(0, min(100, round(q)))


def _finish(rows: _Rows, x: float, y: float, z: float, sigma: float, loss: Loss, c: float, iterations: int) -> Solution:
    """Covariance, residuals, used anchors and quality at (x, y)."""
    sqrt = math.sqrt
    a11 = a12 = a22 = 0.0
    wsum = wr2 = 0.0
    used: list[str] = []
    for ax, ay, dz2, m, aid in rows:
        dx, dy = x - ax, y - ay
        rho = sqrt(dx * dx + dy * dy + dz2)
        r = rho - m
        w = _weight(loss, r, c)
        if rho > 1e-9:
            jx, jy = dx / rho, dy / rho
            a11 += w * jx * jx
            a12 += w * jx * jy
            a22 += w * jy * jy
        wsum += w
        wr2 += w * r * r
        if w >= INLIER_WEIGHT:
            used.append(aid)
    det = a11 * a22 - a12 * a12
    tr = a11 + a22
    if not det > 0 or tr * tr / det > MAX_COND:
        return _refused(FixStatus.DEGENERATE_GEOMETRY, z, tuple(used))
    rms = sqrt(wr2 / wsum) if wsum > 0 else math.inf
    # Prior range sigma, inflated when the (trusted) residuals say the ranges are worse.
    s2 = max(sigma, rms) ** 2 if len(rows) > 2 else sigma * sigma
    sd_x = sqrt(s2 * a22 / det)
    sd_y = sqrt(s2 * a11 / det)
    q = quality_from_sd(sd_x, sd_y, len(used) / len(rows))
    return Solution(FixStatus.OK, x, y, z, sd_x, sd_y, q, rms, tuple(used), iterations)


def _far(rows: _Rows, x: float, y: float) -> bool:
    """Further from every anchor than any measured range allows (with slack)."""
    if not (math.isfinite(x) and math.isfinite(y)):
        return True
    reach = max(r[3] for r in rows) + 5.0
    return min(math.hypot(x - r[0], y - r[1]) for r in rows) > reach


def solve(
    anchors: Sequence[Anchor] | Mapping[str, Anchor],
    ranges: Iterable[Any],
    tag_z: float,
    previous: Solution | tuple[float, float] | None = None,
    *,
    sigma_m: float = DEFAULT_SIGMA_M,
    loss: Loss | str = Loss.CAUCHY,
    max_iterations: int = MAX_ITERATIONS,
) -> Solution:
    """Robust weighted NLLS fix of a tag at height ``tag_z``.

    ``ranges``: ``Range``s (``anchor_id``, ``distance_m``), wire ``UwbRange``s (``anchor``,
    ``distance_m``) or ``(anchor_id, metres)`` tuples; unknown anchors, non-finite or negative
    ranges and repeats are ignored. ``previous``: a starting point (the last fix), else the linear
    solution. ``sigma_m``: the range noise assumed for the covariance and the loss scale.
    """
    rows = _rows(anchors, ranges, tag_z)
    if len(rows) < 3:
        return _refused(FixStatus.TOO_FEW_RANGES, tag_z, tuple(r[4] for r in rows))
    if _collinear(rows):
        return _refused(FixStatus.DEGENERATE_GEOMETRY, tag_z, tuple(r[4] for r in rows))
    loss = Loss(loss)
    sigma = max(sigma_m, 1e-3)
    starts: list[tuple[float, float]] = []
    if isinstance(previous, Solution):
        if previous.ok:
            starts.append((previous.x, previous.y))
    elif previous is not None:
        starts.append((float(previous[0]), float(previous[1])))
    lin = _linear(rows)
    if lin is not None:
        starts.append(lin)
    n = len(rows)
    starts.append((sum(r[0] for r in rows) / n, sum(r[1] for r in rows) / n))
    best: Solution | None = None
    for x0, y0 in starts:
        its = 0
        x, y = x0, y0
        used_loss = loss
        scale = (CAUCHY_K if loss is Loss.CAUCHY else HUBER_K) * sigma
        if loss is Loss.CAUCHY:
            # A convex-ish Huber stage first: Cauchy alone can settle where an outlier pulled the start.
            hx, hy, its, h_ok = _gauss_newton(rows, x, y, Loss.HUBER, HUBER_K * sigma, max_iterations)
            x, y, more, converged = _gauss_newton(rows, hx, hy, loss, scale, max_iterations)
            if not converged and h_ok:
                # Cauchy can crawl when most ranges are biased (deep NLOS): keep the Huber fix.
                x, y, used_loss, scale, converged = hx, hy, Loss.HUBER, HUBER_K * sigma, True
        else:
            x, y, more, converged = _gauss_newton(rows, x, y, loss, scale, max_iterations)
        if not converged or _far(rows, x, y):
            continue
        sol = _finish(rows, x, y, tag_z, sigma, used_loss, scale, its + more)
        if best is None or len(sol.used) > len(best.used):
            best = sol
        if 2 * len(sol.used) > n:  # most ranges agree: good enough, skip the other starts
            return sol
    return best if best is not None else _refused(FixStatus.DIVERGED, tag_z, tuple(r[4] for r in rows))


def solve_linear(
    anchors: Sequence[Anchor] | Mapping[str, Anchor],
    ranges: Iterable[Any],
    tag_z: float,
    previous: Solution | tuple[float, float] | None = None,
    *,
    sigma_m: float = DEFAULT_SIGMA_M,
) -> Solution:
    """The baseline: linear least squares (mean-subtracted squared range equations), no
    robustness. ``previous`` is accepted for a uniform signature and ignored."""
    del previous
    rows = _rows(anchors, ranges, tag_z)
    if len(rows) < 3:
        return _refused(FixStatus.TOO_FEW_RANGES, tag_z, tuple(r[4] for r in rows))
    if _collinear(rows):
        return _refused(FixStatus.DEGENERATE_GEOMETRY, tag_z, tuple(r[4] for r in rows))
    lin = _linear(rows)
    if lin is None:
        return _refused(FixStatus.DEGENERATE_GEOMETRY, tag_z, tuple(r[4] for r in rows))
    return _finish(rows, lin[0], lin[1], tag_z, max(sigma_m, 1e-3), Loss.L2, 1.0, 1)
