"""Relations measured by matching two scans, the way the published relation sets were made.

Kümmerle et al. (2009) obtained the Freiburg relation files "by manually matching laser-range
observations to avoid the errors caused by matching algorithms": a relation is where the second
scan fits onto the first, not what a corrected log's poses say. A corrected log is itself a SLAM
system's output (intel's and aces' are GMapping's, 15 and 30 particles), and its poses scatter about
what the scans show by ~3 cm (docs/mapping.md, "Which reference"). `generate_relations` picks the
pairs from those poses; `match_relations` measures each pair again from its two scans and keeps it
only where the match is unambiguous, a machine's stand-in for the person's check.

The matcher is deliberately not the mapper's (`matcher.icp_refine`: fused 10 cm cells, normals from
a segment's neighbours): a reference made with the mapper's own matcher would favour it. This is
a plain point-to-line ICP after Censi ("An ICP variant using a point-to-line metric", 2008): each
point of one scan against the line through its nearest point of the other scan and that point's
neighbour on the same surface (the next or previous beam, whichever is nearer), found again each
iteration with a k-d tree; Cauchy-weighted residuals; Gauss-Newton. Both ways (the second scan
onto the first and the first onto the second), and the pair kept only when:

- each way finds a line for at least ``min_inliers`` of its points (within ``inlier_m``);
- each way is well posed: the weakest direction of its translation information (the sum of the
  inliers' line normals' outer products) is worth at least ``min_weakest`` points (a corridor seen
  along its length is not: its position along the corridor is a guess);
- the two ways agree within ``agree_m`` / ``agree_rad`` (a look-alike seldom fits both ways alike);
- the match lies within ``max_shift_m`` / ``max_shift_rad`` of the reference relation: the corrected
  log is right to a few centimetres, so a match far from it found another place that looks alike;
- no second answer nearly as good lies along the weakest direction (``probe_m``): down a corridor
  two scans often fit at two places 0.2-0.3 m apart, and the pair cannot say which is true;
- its neighbours do not all disagree: the pairs a scan or two beside either end, matched on their
  own, predict this one through the reference's short step between them.

Pure: numpy and scipy's k-d tree, no clock; the same input gives the same output.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from fleetlink.agent.mapping.relations import Relation, nearest_times
from fleetlink.shared.se2 import compose, inverse, relative

__all__ = ["LineScan", "MatchedRelations", "PairMatch", "PairMatchConfig", "match_pair", "match_relations"]

Pose = tuple[float, float, float]
FloatArray = npt.NDArray[np.float64]
Scan = tuple[FloatArray, FloatArray]  # (ranges m, angles rad in the sensor frame)


DEFAULT_JOIN_M = 0.3


@dataclass(frozen=True, slots=True)
class PairMatchConfig:
    iterations: int = 30
    # Correspondences further than this from their nearest point are ignored: 0.3 m at first (the
    # reference may be a few centimetres off, a revisit's a little more), shrinking to 0.1 m.
    reach_start_m: float = 0.3
    reach_end_m: float = 0.1
    cauchy_m: float = 0.03  # the residual scale: a wall's thickness in a 2D scan's noise
    join_m: float = DEFAULT_JOIN_M  # neighbouring beams at most this far apart lie on one surface
    inlier_m: float = 0.05  # a point within this of its line (and 0.1 m of a point) is an inlier
    min_inliers: float = 0.3  # share of a scan's points, each way
    min_weakest: float = 9.0  # points' worth of information along the weakest direction, each way
    agree_m: float = 0.02
    agree_rad: float = math.radians(0.5)
    max_shift_m: float = 0.2
    max_shift_rad: float = math.radians(3.0)
    # Ambiguity: matched again from guesses this far along the weakest direction; another answer
    # this far from the first that finds lines for nearly as many points makes the pair ambiguous.
    probe_m: tuple[float, ...] = (-0.25, 0.25)
    rival_m: float = 0.05
    rival_inliers: float = 0.9
    probe_iterations: int = 15  # enough to settle in a basin; a probe only asks whether one exists
    # Neighbours: pairs up to this many scans beside either end; a match must agree with one of
    # their predictions within neighbour_m / neighbour_rad (when any was kept).
    neighbours: int = 2
    neighbour_m: float = 0.1
    neighbour_rad: float = math.radians(1.5)
    neighbour_step_m: float = 0.5  # and whose scan is this close to this pair's by the reference


@dataclass(frozen=True, slots=True)
class PairMatch:
    pose: Pose  # the matched scan's pose in the reference scan's frame
    inliers: int
    points: int
    weakest: float  # points' worth of information along the weakest direction
    weak_axis: tuple[float, float] = (1.0, 0.0)  # that direction, a unit vector in the reference frame


class LineScan:
    """One scan's endpoints in the robot frame, in beam order, and which neighbours share a surface."""

    def __init__(self, points: FloatArray, joined: npt.NDArray[np.bool_]) -> None:
        self.points = points
        self.joined = joined  # joined[k]: points k and k + 1 lie on one surface
        self.tree = cKDTree(points) if len(points) else None
        # Per segment k (point k to k + 1), its unit normal; padded with one unjoined segment at
        # each end, so segment j - 1 of point 0 (index -1 here, row 0 below) needs no clamping.
        n = len(points)
        t = np.diff(points, axis=0) if n > 1 else np.zeros((0, 2))
        length = np.hypot(t[:, 0], t[:, 1])
        ok = joined[: max(n - 1, 0)] & (length > 1e-9)
        safe = np.where(ok, length, 1.0)
        self._seg_ok = np.concatenate(([False], ok, [False]))  # row k + 1: segment k
        self._seg_normal = np.vstack(
            (np.zeros((1, 2)), np.column_stack((-t[:, 1] / safe, t[:, 0] / safe)), np.zeros((1, 2)))
        )
        self._padded = np.vstack((points[:1], points, points[-1:])) if n else np.zeros((0, 2))  # row k + 1: point k

    @classmethod
    def from_ranges(
        cls,
        ranges: FloatArray,
        angles: FloatArray,
        *,
        max_range: float = math.inf,
        mount: Pose = (0.0, 0.0, 0.0),
        join_m: float = DEFAULT_JOIN_M,
    ) -> LineScan:
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(angles, dtype=np.float64)
        if r.shape != a.shape or r.ndim != 1:
            raise ValueError(f"a scan's ranges and angles must be 1-D and of one length, got {r.shape} and {a.shape}")
        order = np.argsort(a, kind="stable")
        r, a = r[order], a[order]
        beam = np.arange(len(r))
        with np.errstate(invalid="ignore"):
            # The mapper's "no return" convention; a beam without a finite angle is dropped too.
            hit = np.isfinite(r) & (r > 0.0) & (r < max_range) & np.isfinite(a)
        r, a, beam = r[hit], a[hit], beam[hit]
        c, s = math.cos(mount[2]), math.sin(mount[2])
        lx, ly = r * np.cos(a), r * np.sin(a)
        pts = np.column_stack((mount[0] + c * lx - s * ly, mount[1] + s * lx + c * ly))
        gap = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
        # One missing beam between two points does not split a surface; a larger gap does.
        joined = np.zeros(len(pts), dtype=bool)
        joined[:-1] = (gap <= join_m) & (np.diff(beam) <= 2)
        return cls(pts, joined)


def _transform(points: FloatArray, pose: Pose) -> FloatArray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    x, y = points[:, 0], points[:, 1]
    return np.column_stack((pose[0] + c * x - s * y, pose[1] + s * x + c * y))


def _lines(ref: LineScan, q: FloatArray, reach: float) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """Each point's nearest reference point within ``reach`` and the unit normal of its line;
    ``has``: such a point with a neighbour on its surface (a line). The
    line runs to whichever neighbour on the surface is nearer to the point (Censi's second point)."""
    assert ref.tree is not None
    n = len(ref.points)
    # Bounded: the tree stops looking beyond reach (those come back as n, at an infinite distance).
    _, j = ref.tree.query(q, distance_upper_bound=reach)
    j = np.asarray(j, dtype=np.intp)
    found = j < n
    j[~found] = 0
    after_ok, before_ok = ref._seg_ok[j + 1], ref._seg_ok[j]  # segments j and j - 1
    d_next = np.where(after_ok, np.hypot(*(ref._padded[j + 2] - q).T), np.inf)
    d_prev = np.where(before_ok, np.hypot(*(ref._padded[j] - q).T), np.inf)
    seg = np.where(d_next <= d_prev, j + 1, j)
    has = found & (after_ok | before_ok)
    return ref.points[j], ref._seg_normal[seg], has


def match_pair(
    ref: LineScan, scan: LineScan, guess: Pose, config: PairMatchConfig = PairMatchConfig(), *, iterations: int = 0
) -> PairMatch | None:
    """``scan``'s pose in ``ref``'s frame, from ``guess``; None when too few points find a line.
    ``iterations`` (> 0) caps the Gauss-Newton steps below ``config.iterations``."""
    if ref.tree is None or len(scan.points) < 3:
        return None
    x, y, th = guess
    for it in range(min(config.iterations, iterations or config.iterations)):
        q = _transform(scan.points, (x, y, th))
        reach = max(config.reach_end_m, config.reach_start_m - (config.reach_start_m - config.reach_end_m) * it / 5)
        a, normal, has = _lines(ref, q, reach)
        if np.count_nonzero(has) < 3:
            return None
        nu, qu = normal[has], q[has]
        r = np.einsum("ij,ij->i", qu - a[has], nu)
        lever = nu[:, 1] * (qu[:, 0] - x) - nu[:, 0] * (qu[:, 1] - y)  # d(residual)/d(theta)
        jac = np.column_stack((nu, lever))
        w = 1.0 / (1.0 + (r / config.cauchy_m) ** 2)
        h = jac.T @ (jac * w[:, None])
        g = jac.T @ (w * r)
        try:
            step = -np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            return None
        x, y, th = x + float(step[0]), y + float(step[1]), th + float(step[2])
        if it >= 5 and abs(step[0]) + abs(step[1]) < 1e-5 and abs(step[2]) < 1e-5:
            break
    q = _transform(scan.points, (x, y, th))
    a, normal, has = _lines(ref, q, config.reach_end_m)
    r = np.abs(np.einsum("ij,ij->i", q - a, normal))
    inl = has & (r <= config.inlier_m)
    nu = normal[inl]
    values, vectors = np.linalg.eigh(nu.T @ nu)
    axis = (float(vectors[0, 0]), float(vectors[1, 0]))
    pose = (x, y, math.remainder(th, 2.0 * math.pi))
    return PairMatch(pose, int(np.count_nonzero(inl)), len(scan.points), float(values[0]), axis)


@dataclass(slots=True)
class MatchedRelations:
    relations: list[Relation]
    refused: dict[str, int] = field(default_factory=dict)  # reason -> relations not kept

    def summary(self) -> str:
        total = len(self.relations) + sum(self.refused.values())
        why = ", ".join(f"{n} {reason}" for reason, n in sorted(self.refused.items()) if n)
        return f"{len(self.relations)} of {total} relations kept by matching their scans" + (
            f" (refused: {why})" if why else ""
        )


def _refusal(m: PairMatch | None, config: PairMatchConfig) -> str | None:
    if m is None or m.inliers < config.min_inliers * m.points:
        return "few points on a line"
    if m.weakest < config.min_weakest:
        return "ill-posed"
    return None


def _rival(ref: LineScan, scan: LineScan, best: PairMatch, config: PairMatchConfig) -> bool:
    """Another answer, as good, elsewhere along the weakest direction: down a corridor two scans
    often fit at two positions 0.2-0.3 m apart (door frames, repeated bays), and which one is true
    the pair cannot say, so it is no reference."""
    x, y, th = best.pose
    ax, ay = best.weak_axis
    for offset in config.probe_m:
        m = match_pair(ref, scan, (x + offset * ax, y + offset * ay, th), config, iterations=config.probe_iterations)
        if m is None or math.hypot(m.pose[0] - x, m.pose[1] - y) <= config.rival_m:
            continue
        m = match_pair(ref, scan, m.pose, config)  # settled: a probe cut short is not yet a rival
        if (
            m is not None
            and _refusal(m, config) is None
            and m.inliers >= config.rival_inliers * best.inliers
            and math.hypot(m.pose[0] - x, m.pose[1] - y) > config.rival_m
        ):
            return True
    return False


def match_relations(
    relations: Sequence[Relation],
    times: Sequence[float],
    scans: Sequence[Scan],
    *,
    max_range: float = math.inf,
    mount: Pose = (0.0, 0.0, 0.0),
    config: PairMatchConfig = PairMatchConfig(),
    tolerance_s: float = 1e-3,
) -> MatchedRelations:
    """Each relation measured again by matching its two scans (``scans[k]`` taken at ``times[k]``),
    from the relation itself; kept where the match passes the gates above, in the input's order."""
    if len(scans) != len(times):
        raise ValueError(f"times and scans differ in length: {len(times)} and {len(scans)}")
    order = np.argsort(np.asarray(times, dtype=np.float64), kind="stable")
    sorted_t = np.asarray(times, dtype=np.float64)[order]
    cache: dict[int, LineScan] = {}

    def index_at(t: float) -> int | None:
        best = int(nearest_times(sorted_t, np.array([t]), tolerance_s)[0])  # in time order
        return None if best < 0 else best

    def scan(k: int) -> LineScan:
        if k not in cache:
            i = int(order[k])
            cache[k] = LineScan.from_ranges(
                scans[i][0], scans[i][1], max_range=max_range, mount=mount, join_m=config.join_m
            )
        return cache[k]

    refused: dict[str, int] = {}
    kept: dict[tuple[int, int], tuple[Relation, Pose]] = {}  # (i, j) in time order -> (reference, match)
    for rel in relations:
        i, j = index_at(rel.t1), index_at(rel.t2)
        if i is None or j is None:
            reason: str | None = "no scan at its time"
        elif i == j:
            reason = "one scan at both times"
        elif (i, j) in kept:
            reason = "a repeat"  # the same pair again: one relation is measured once
        else:
            z = (rel.dx, rel.dy, rel.dtheta)
            first, second = scan(i), scan(j)
            there = match_pair(first, second, z, config)
            reason = _refusal(there, config)
            back = match_pair(second, first, inverse(z), config) if reason is None else None
            reason = reason or _refusal(back, config)
            if reason is None and there is not None and back is not None:
                loop = compose(there.pose, back.pose)  # identity when the two ways agree
                shift = compose(inverse(z), there.pose)
                if _beyond(loop, config.agree_m, config.agree_rad):
                    reason = "the two ways disagree"
                elif _beyond(shift, config.max_shift_m, config.max_shift_rad):
                    reason = "far from the reference"
                elif _rival(first, second, there, config):
                    reason = "ambiguous"
                else:
                    # Halfway between the two ways' answers: the pair's relation does not depend on
                    # which scan was matched onto which.
                    dx, dy, dth = relative(there.pose, inverse(back.pose))
                    kept[(i, j)] = (rel, compose(there.pose, (0.5 * dx, 0.5 * dy, 0.5 * dth)))
        if reason is not None:
            refused[reason] = refused.get(reason, 0) + 1
    out = MatchedRelations([], refused)
    for (i, j), (rel, pose) in kept.items():
        if _neighbours_disagree(i, j, kept, config):
            refused["its neighbours disagree"] = refused.get("its neighbours disagree", 0) + 1
            continue
        out.relations.append(Relation(rel.t1, rel.t2, pose[0], pose[1], math.remainder(pose[2], 2 * math.pi)))
    return out


def _beyond(p: Pose, metres: float, radians: float) -> bool:
    return math.hypot(p[0], p[1]) > metres or abs(math.remainder(p[2], 2.0 * math.pi)) > radians


def _neighbours_disagree(
    i: int, j: int, kept: dict[tuple[int, int], tuple[Relation, Pose]], config: PairMatchConfig
) -> bool:
    """A match that none of its neighbours' matches bears out. The scans a step or two beside either
    end, matched on their own, predict this pair's relation through the reference's short step
    between the neighbour and this scan (a corrected log is good to a few centimetres over a step):
    a match that disagrees with every such prediction picked a second fit the pair alone could not
    rule out. Only neighbours within ``neighbour_step_m`` count (the reference's error grows with
    the step); with none the match stands on its own. A good match whose only neighbour is wrong
    goes with it: a reference is better a relation short than one wrong."""
    rel, match = kept[(i, j)]
    ref = (rel.dx, rel.dy, rel.dtheta)
    seen = 0
    for d in range(-config.neighbours, config.neighbours + 1):
        if d == 0:
            continue
        for a, b in ((i, j + d), (i + d, j)):
            other = kept.get((a, b))
            if other is None:
                continue
            oref = (other[0].dx, other[0].dy, other[0].dtheta)
            if a == i:  # same first scan: (i, j) = (i, j') then the reference's step j' -> j
                step = compose(inverse(oref), ref)
                predicted = compose(other[1], step)
            else:  # same second scan: (i, j) = the reference's step i -> i' then (i', j)
                step = compose(ref, inverse(oref))
                predicted = compose(step, other[1])
            if math.hypot(step[0], step[1]) > config.neighbour_step_m:
                continue  # a long step: the reference is not good enough over it to judge by
            seen += 1
            if not _beyond(relative(match, predicted), config.neighbour_m, config.neighbour_rad):
                return False
    return seen > 0
