"""Relation errors (Kümmerle et al. 2009, "On measuring the accuracy of SLAM algorithms").

A *relation* says where the robot was at time ``t2`` as seen from where it was at time ``t1``: the
pose at ``t2`` in the frame of the pose at ``t1`` (SE(2): ``dx dy dtheta``). A trajectory is scored
by computing the same relative pose from its own poses at ``t1`` and ``t2`` and comparing:

    error = est ⊖ ref = ref^-1 ⊕ est      (the paper's ⊖: the estimated relation seen from the reference one)
    translational error = |translation of error|   (m; in 2D equal to |est_xy - ref_xy|)
    rotational error    = |wrap(est_theta - ref_theta)|   (rad)

Only relative poses are compared, so the trajectory may live in any frame: no alignment is needed.
The absolute trajectory error (ATE) does need one: ``align_se2`` gives the rigid transform that
takes a trajectory's positions onto the reference's (least squares), ``transform_xy`` applies it.

Text formats (relations as in the Freiburg relation files; trajectories as replay writes them):

    relations   ``t1 t2 x y z roll pitch yaw`` per line; 2D uses x, y and yaw (z, roll, pitch ignored)
    trajectory  ``t x y theta`` per line (``fleetlink map replay``'s ``trajectory.txt``)

Blank lines and lines starting with ``#`` are skipped in both. Pure: numpy and the standard library,
text in and text out, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.matcher import scan_normals
from fleetlink.agent.mapping.scan import segment_labels
from fleetlink.shared.se2 import compose, relative

__all__ = [
    "DEFAULT_LOCAL_S",
    "DEFAULT_MAX_DISTANCE_M",
    "DEFAULT_MAX_RELATIONS",
    "ErrorStats",
    "Relation",
    "RelationScore",
    "align_se2",
    "format_relations",
    "format_score",
    "generate_relations",
    "indistinct_times",
    "nearest_times",
    "parse_relations",
    "parse_trajectory",
    "relation",
    "score",
    "transform_xy",
    "view_overlap",
]

Pose = tuple[float, float, float]
FloatArray = npt.NDArray[np.float64]
Scan = tuple[FloatArray, FloatArray]  # (ranges m, angles rad in the sensor frame)

# Scan pairs further apart than this get no relation. The reference poses' own heading error grows
# into the relation's translation with distance (0.5 deg at 3 m is 2.6 cm), and beyond a few metres
# two views of an office share little that a person or a matcher could check the relation against.
DEFAULT_MAX_DISTANCE_M = 3.0
# Without scans, two views overlap when their headings differ by at most this much (a 180 deg
# scanner then still shares half its field of view).
DEFAULT_MAX_HEADING_RAD = math.pi / 2
DEFAULT_MIN_OVERLAP = 0.5  # view_overlap: share of one scan's endpoints the other sees
DEFAULT_OCCLUSION_M = 0.3  # an endpoint this far behind the other scan's reading still counts as seen
# An endpoint's surface, for telling which side of it a sensor is on: its neighbours along the scan,
# broken where the mapper's segmentation breaks (scan.segment_labels: gaps over 0.3 m, or 5 times
# their neighbour's).
SURFACE_BREAK_M = 0.3
SURFACE_BREAK_RATIO = 5.0
# intel (910 scans) gives about 9 800 relations with its scans, 12 600 without; a robot that stands
# still for a long time adds pairs quadratically, so the set is thinned (evenly, by stride) beyond this.
DEFAULT_MAX_RELATIONS = 20_000
DEFAULT_LOCAL_S = 20.0
# Trajectory and relation times are the same log timestamps written as text (6 decimals in CARMEN
# logs): a relation's time takes the nearest trajectory time within 1 ms, which absorbs rounding.
# Scans can be nearer than that (the published intel.clf has 1 479 pairs of FLASER lines < 1 ms
# apart, 6 us at the least: IPC stamps of a burst), so the nearest decides; two trajectory times the
# text cannot tell apart (``RESOLUTION_S``) are an error, and a relation time as near to two
# trajectory times as that resolution can tell is counted missing.
DEFAULT_TOLERANCE_S = 1e-3
RESOLUTION_S = 1e-6

RELATION_FIELDS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")
TRAJECTORY_FIELDS = ("t", "x", "y", "theta")


@dataclass(frozen=True, slots=True)
class Relation:
    t1: float  # s
    t2: float  # s
    dx: float  # m: the pose at t2 in the frame of the pose at t1
    dy: float  # m
    dtheta: float  # rad


relation = relative
"""p1^-1 (+) p2: the pose p2 seen from p1 (the relation a file line holds)."""


# -- text ------------------------------------------------------------------------------------------


def _fields(lines: Iterable[str], names: tuple[str, ...]) -> Iterable[tuple[int, list[float]]]:
    """(line number, numbers) per data line; ValueError naming the line and what is wrong."""
    for number, raw in enumerate(lines, start=1):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        toks = text.split()
        if len(toks) != len(names):
            raise ValueError(f"line {number}: expected {len(names)} fields ({' '.join(names)}), found {len(toks)}")
        values = []
        for name, tok in zip(names, toks, strict=True):
            try:
                v = float(tok)
            except ValueError:
                raise ValueError(f"line {number}: {name} is not a number: {tok!r}") from None
            if not math.isfinite(v):
                raise ValueError(f"line {number}: {name} is not finite: {tok!r}")
            values.append(v)
        yield number, values


def parse_relations(lines: Iterable[str]) -> list[Relation]:
    """Relations from ``t1 t2 x y z roll pitch yaw`` lines (z, roll and pitch are ignored in 2D).
    Yaw is kept as written (``score`` wraps the difference), so a written set reads back bit for bit."""
    return [Relation(v[0], v[1], v[2], v[3], v[7]) for _, v in _fields(lines, RELATION_FIELDS)]


def format_relations(relations: Iterable[Relation]) -> str:
    """The relations format; ``repr`` of each float is the shortest text that reads back to it."""
    return "".join(f"{r.t1!r} {r.t2!r} {r.dx!r} {r.dy!r} 0 0 0 {r.dtheta!r}\n" for r in relations)


def parse_trajectory(lines: Iterable[str]) -> tuple[list[float], list[Pose]]:
    """Times and poses from ``t x y theta`` lines (replay's ``format_trajectory``)."""
    times: list[float] = []
    poses: list[Pose] = []
    for _, v in _fields(lines, TRAJECTORY_FIELDS):
        times.append(v[0])
        poses.append((v[1], v[2], v[3]))
    return times, poses


# -- a complete relation set ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _View:
    """One scan placed in the world: its sensor pose, its endpoints, its beams sorted by angle."""

    sensor: Pose
    points: FloatArray  # (n, 2) world endpoints of the beams that hit something
    span: float  # rad: from the first beam to the last
    bounds: FloatArray  # rad from the first beam: midpoints between neighbouring beams, sorted
    first: float  # rad: the first beam's angle in the sensor frame
    half_step: float  # rad: half the beam spacing (the field of view reaches this far past the ends)
    reach: FloatArray  # m per sorted beam: its reading, or the maximum range where it had no return
    normals: FloatArray  # (n, 2) world unit normal of each endpoint's surface, facing the sensor; NaN: none


def _view(pose: Pose, scan: Scan, max_range: float, mount: Pose) -> _View:
    ranges = np.asarray(scan[0], dtype=np.float64)
    angles = np.asarray(scan[1], dtype=np.float64)
    if ranges.shape != angles.shape or ranges.ndim != 1:
        raise ValueError(
            f"a scan's ranges and angles must be 1-D and of one length, got {ranges.shape} and {angles.shape}"
        )
    sensor = compose(pose, mount)
    # 0, NaN, inf and readings at the maximum are "no return" (the mapper's convention): the beam
    # saw nothing up to its maximum range.
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(ranges) & (ranges > 0.0) & (ranges < max_range)
    c, s = math.cos(sensor[2]), math.sin(sensor[2])
    r, a = ranges[hit], angles[hit]
    lx, ly = r * np.cos(a), r * np.sin(a)
    points = np.column_stack((sensor[0] + c * lx - s * ly, sensor[1] + s * lx + c * ly))
    # Neighbours along the scan in beam order: hits sorted by angle (a log's beams usually are).
    along = np.argsort(a, kind="stable")
    local = np.column_stack((lx, ly))[along]
    normals = np.full((len(a), 2), np.nan)
    normals[along] = scan_normals(local, segment_labels(local, SURFACE_BREAK_M, SURFACE_BREAK_RATIO))
    normals = np.column_stack((c * normals[:, 0] - s * normals[:, 1], s * normals[:, 0] + c * normals[:, 1]))
    order = np.argsort(angles, kind="stable")
    sorted_angles = angles[order]
    first = float(sorted_angles[0]) if len(sorted_angles) else 0.0
    step = float(np.median(np.diff(sorted_angles))) if len(sorted_angles) > 1 else 0.0
    reach = np.where(hit[order], ranges[order], max_range)
    rel = sorted_angles - first
    span = float(rel[-1]) if len(rel) else 0.0
    return _View(sensor, points, span, (rel[1:] + rel[:-1]) / 2.0, first, step / 2.0, reach, normals)


def _seen_share(a: _View, b: _View, max_range: float, occlusion_m: float, facing_only: bool = True) -> float:
    """Share of a's endpoints inside b's field of view and range and not hidden behind what b saw;
    with ``facing_only``, on surfaces that face b's sensor (an endpoint with no surface, alone
    between gaps, counts as facing)."""
    if len(a.points) == 0 or len(b.reach) == 0:
        return 0.0
    c, s = math.cos(b.sensor[2]), math.sin(b.sensor[2])
    dx, dy = a.points[:, 0] - b.sensor[0], a.points[:, 1] - b.sensor[1]
    bx, by = c * dx + s * dy, -s * dx + c * dy
    dist = np.hypot(bx, by)
    # Bearing from b's first beam, within [-half a step, 2 pi - half a step): a 360 deg scan's wrap
    # needs no special case.
    rel = (np.arctan2(by, bx) - b.first + b.half_step) % (2.0 * math.pi) - b.half_step
    in_fov = rel <= b.span + b.half_step
    nearest = np.searchsorted(b.bounds, rel)
    visible = in_fov & (dist <= max_range) & (dist <= b.reach[nearest] + occlusion_m)
    if facing_only:
        # A surface turned away from b is the far side of a wall from b: within ``occlusion_m`` of
        # what b saw when the wall is thin, but not what b saw.
        visible &= ~(a.normals[:, 0] * dx + a.normals[:, 1] * dy > 0.0)  # NaN compares False: kept
    return float(visible.mean())


def view_overlap(
    pose_a: Pose,
    scan_a: Scan,
    pose_b: Pose,
    scan_b: Scan,
    *,
    max_range: float = math.inf,
    mount: Pose = (0.0, 0.0, 0.0),
    occlusion_m: float = DEFAULT_OCCLUSION_M,
    facing_only: bool = True,
) -> float:
    """How much two scans see of each other, 0..1: the larger of the two shares of one scan's
    endpoints that fall inside the other's field of view and range without lying more than
    ``occlusion_m`` behind the other's reading on the nearest beam (a wall between them hides them),
    and, with ``facing_only``, on surfaces that face the other's sensor: two scans on either side of
    a partition thinner than ``occlusion_m`` see its two faces, not the same thing.

    The larger, not the smaller: a 180 deg scanner that moves 1 m down a corridor leaves behind the
    side-wall points it saw beside it (often half its endpoints) while everything the second scan
    sees lies in the first one's view. On intel the smaller share is below 0.5 for a quarter of
    consecutive scan pairs; the larger for 1 %."""
    va, vb = _view(pose_a, scan_a, max_range, mount), _view(pose_b, scan_b, max_range, mount)
    return max(
        _seen_share(va, vb, max_range, occlusion_m, facing_only),
        _seen_share(vb, va, max_range, occlusion_m, facing_only),
    )


def generate_relations(
    times: Sequence[float],
    poses: Sequence[Pose],
    *,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    max_heading_rad: float = DEFAULT_MAX_HEADING_RAD,
    scans: Sequence[Scan] | None = None,
    max_range: float = math.inf,
    mount: Pose = (0.0, 0.0, 0.0),
    min_overlap: float = DEFAULT_MIN_OVERLAP,
    occlusion_m: float = DEFAULT_OCCLUSION_M,
    facing_only: bool = True,
    max_relations: int = DEFAULT_MAX_RELATIONS,
) -> list[Relation]:
    """A complete relation set from reference poses (a corrected log's): every pair of scans, however
    far apart in time, whose poses lie within ``max_distance_m`` and whose views overlap.

    Overlap: with ``scans`` (ranges, angles per pose, sensor frame; ``mount`` is the sensor on the
    robot, readings >= ``max_range`` are no return), ``view_overlap`` >= ``min_overlap`` (``facing_only``:
    an endpoint counts only on a surface facing the other sensor; False counts the far faces of walls
    thinner than ``occlusion_m`` too, as sets were drawn until 2026-12-07); without, headings within
    ``max_heading_rad``. Pairs come in log order (i < j, by i then j); beyond
    ``max_relations`` every k-th is kept (k the smallest stride that fits), which thins them evenly
    over the log and gives the same set every time. Times must be distinct (``indistinct_times``;
    ValueError): a relation names its two scans by them.
    """
    n = len(times)
    if len(poses) != n:
        raise ValueError(f"times and poses differ in length: {n} and {len(poses)}")
    if scans is not None and len(scans) != n:
        raise ValueError(f"scans and poses differ in length: {len(scans)} and {n}")
    if not max_distance_m > 0:
        raise ValueError(f"max_distance_m must be > 0, got {max_distance_m}")
    if not 0.0 <= min_overlap <= 1.0:
        raise ValueError(f"min_overlap must be within 0..1, got {min_overlap}")
    if max_relations < 1:
        raise ValueError(f"max_relations must be >= 1, got {max_relations}")
    if not max_range > 0:
        raise ValueError(f"max_range must be > 0, got {max_range}")
    problem = indistinct_times(times)
    if problem:
        raise ValueError(problem)
    if n < 2:
        return []
    p = np.asarray(poses, dtype=np.float64).reshape(n, 3)
    # One row of the pair matrix at a time: memory stays O(n) for long logs.
    rows = []
    for i in range(n - 1):
        rest = p[i + 1 :]
        near = np.hypot(rest[:, 0] - p[i, 0], rest[:, 1] - p[i, 1]) <= max_distance_m
        if scans is None:
            near &= np.abs((rest[:, 2] - p[i, 2] + math.pi) % (2.0 * math.pi) - math.pi) <= max_heading_rad
        j = np.nonzero(near)[0] + i + 1
        rows.append(np.column_stack((np.full(len(j), i), j)))
    pairs = np.concatenate(rows).astype(np.intp)
    if scans is not None:
        views = [_view(poses[k], scans[k], max_range, mount) for k in range(n)]
        keep = [
            _seen_share(views[i], views[j], max_range, occlusion_m, facing_only) >= min_overlap
            or _seen_share(views[j], views[i], max_range, occlusion_m, facing_only) >= min_overlap
            for i, j in pairs.tolist()
        ]
        pairs = pairs[np.array(keep, dtype=bool).reshape(-1)]
    if len(pairs) > max_relations:
        pairs = pairs[:: math.ceil(len(pairs) / max_relations)]
    out = []
    for i, j in pairs.tolist():
        dx, dy, dth = relation(poses[i], poses[j])
        out.append(Relation(float(times[i]), float(times[j]), dx, dy, dth))
    return out


# -- scoring ---------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ErrorStats:
    """Errors over a set of relations. Standard deviations are population ones (divide by n); an
    empty set has count 0 and NaN everywhere else."""

    count: int
    trans_mean_m: float
    trans_std_m: float
    trans_sq_mean_m2: float  # mean squared translational error (the published tool reports both)
    trans_max_m: float
    rot_mean_rad: float
    rot_std_rad: float
    rot_sq_mean_rad2: float
    rot_max_rad: float

    @property
    def rot_mean_deg(self) -> float:
        return math.degrees(self.rot_mean_rad)

    @property
    def rot_std_deg(self) -> float:
        return math.degrees(self.rot_std_rad)

    @classmethod
    def of(cls, trans_m: FloatArray, rot_rad: FloatArray) -> ErrorStats:
        if len(trans_m) == 0:
            nan = math.nan
            return cls(0, nan, nan, nan, nan, nan, nan, nan, nan)
        return cls(
            count=len(trans_m),
            trans_mean_m=float(trans_m.mean()),
            trans_std_m=float(trans_m.std()),
            trans_sq_mean_m2=float((trans_m**2).mean()),
            trans_max_m=float(trans_m.max()),
            rot_mean_rad=float(rot_rad.mean()),
            rot_std_rad=float(rot_rad.std()),
            rot_sq_mean_rad2=float((rot_rad**2).mean()),
            rot_max_rad=float(rot_rad.max()),
        )

    def as_dict(self) -> dict[str, float | int | None]:
        """JSON-ready; None where the set is empty (JSON has no NaN)."""
        values: dict[str, float] = {
            "trans_mean_m": self.trans_mean_m,
            "trans_std_m": self.trans_std_m,
            "trans_sq_mean_m2": self.trans_sq_mean_m2,
            "trans_max_m": self.trans_max_m,
            "rot_mean_rad": self.rot_mean_rad,
            "rot_std_rad": self.rot_std_rad,
            "rot_sq_mean_rad2": self.rot_sq_mean_rad2,
            "rot_max_rad": self.rot_max_rad,
            "rot_mean_deg": self.rot_mean_deg,
            "rot_std_deg": self.rot_std_deg,
        }
        out: dict[str, float | int | None] = {"count": self.count}
        out.update({k: (v if self.count else None) for k, v in values.items()})
        return out


@dataclass(frozen=True, slots=True)
class RelationScore:
    count: int  # relations scored
    missing: int  # relations with t1 or t2 not in the trajectory (not scored)
    local_s: float  # |t2 - t1| below this: local, else revisit
    all: ErrorStats
    local: ErrorStats
    revisit: ErrorStats

    def as_dict(self) -> dict[str, object]:
        return {
            "count": self.count,
            "missing": self.missing,
            "local_s": self.local_s,
            "all": self.all.as_dict(),
            "local": self.local.as_dict(),
            "revisit": self.revisit.as_dict(),
        }


def nearest_times(sorted_times: FloatArray, t: FloatArray, tolerance_s: float) -> npt.NDArray[np.intp]:
    """Index into sorted_times of the time nearest each t, or -1 where none is within tolerance or
    two are equally near (to ``RESOLUTION_S``)."""
    if len(sorted_times) == 0:
        return np.full(len(t), -1, dtype=np.intp)
    hi = np.clip(np.searchsorted(sorted_times, t), 0, len(sorted_times) - 1)
    lo = np.maximum(hi - 1, 0)
    d_lo, d_hi = np.abs(sorted_times[lo] - t), np.abs(sorted_times[hi] - t)
    best = np.where(d_lo <= d_hi, lo, hi)
    tied = (lo != hi) & (np.abs(d_lo - d_hi) < RESOLUTION_S)
    return np.where((np.minimum(d_lo, d_hi) <= tolerance_s) & ~tied, best, -1)


def indistinct_times(times: Sequence[float] | FloatArray) -> str | None:
    """Why these times cannot name poses (two less than ``RESOLUTION_S`` apart: a relation could not
    tell which it means), or None. Corrected logs written with ``%g`` stamps (every scan
    ``1.01893e+09``) or none (every scan 0) have such times; their scans can be named by index."""
    t = np.sort(np.asarray(times, dtype=np.float64).reshape(-1))
    close = np.nonzero(np.diff(t) < RESOLUTION_S)[0]
    if not len(close):
        return None
    k = int(close[0])
    return (
        f"times {float(t[k])!r} and {float(t[k + 1])!r} are less than {RESOLUTION_S:g} s apart"
        f" ({len(close)} such neighbours): a relation could not tell which pose it means"
    )


def score(
    trajectory_times: Sequence[float],
    trajectory_poses: Sequence[Pose],
    relations: Sequence[Relation],
    *,
    local_s: float = DEFAULT_LOCAL_S,
    tolerance_s: float = DEFAULT_TOLERANCE_S,
) -> RelationScore:
    """Score a trajectory against relations. A relation's times must each match a trajectory time
    within ``tolerance_s``, the nearest (no interpolation: the relations are made at scan times); one
    that does not, or lies as near to two, is counted in ``missing``. Trajectory times may come in any
    order but must lie at least ``RESOLUTION_S`` apart, or no relation could tell which pose it means
    (ValueError)."""
    n = len(trajectory_times)
    if len(trajectory_poses) != n:
        raise ValueError(f"trajectory times and poses differ in length: {n} and {len(trajectory_poses)}")
    if not tolerance_s >= 0:
        raise ValueError(f"tolerance_s must be >= 0, got {tolerance_s}")
    t = np.asarray(trajectory_times, dtype=np.float64).reshape(n)
    p = np.asarray(trajectory_poses, dtype=np.float64).reshape(n, 3)
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        raise ValueError("the trajectory has non-finite times or poses")
    order = np.argsort(t, kind="stable")
    t, p = t[order], p[order]
    problem = indistinct_times(t)
    if problem:
        raise ValueError(f"trajectory {problem}")
    r = np.array([(x.t1, x.t2, x.dx, x.dy, x.dtheta) for x in relations], dtype=np.float64).reshape(-1, 5)
    i1, i2 = nearest_times(t, r[:, 0], tolerance_s), nearest_times(t, r[:, 1], tolerance_s)
    found = (i1 >= 0) & (i2 >= 0)
    r, a, b = r[found], p[i1[found]], p[i2[found]]
    # The estimated relation a^-1 ⊕ b, then error = ref^-1 ⊕ est.
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    est_x, est_y = c * dx + s * dy, -s * dx + c * dy
    est_th = b[:, 2] - a[:, 2]
    # |R(-theta_ref) (est_xy - ref_xy)| = |est_xy - ref_xy|: the rotation keeps the length.
    trans = np.hypot(est_x - r[:, 2], est_y - r[:, 3])
    rot = np.abs((est_th - r[:, 4] + math.pi) % (2.0 * math.pi) - math.pi)
    is_local = np.abs(r[:, 1] - r[:, 0]) < local_s
    return RelationScore(
        count=int(found.sum()),
        missing=int((~found).sum()),
        local_s=local_s,
        all=ErrorStats.of(trans, rot),
        local=ErrorStats.of(trans[is_local], rot[is_local]),
        revisit=ErrorStats.of(trans[~is_local], rot[~is_local]),
    )


def format_score(result: RelationScore, unit: str = "s") -> str:
    """The table ``fleetlink map score`` prints; ``unit``: what the times count (``scans`` when the
    relations name scans by index)."""
    lines = [
        f"{result.count} relations scored, {result.missing} missing (a time not in the trajectory)",
        f"{'':<22} {'count':>6} {'translational m':>17} {'max m':>7} {'rotational deg':>15}",
    ]
    for name, stats in (
        ("all", result.all),
        (f"local (< {result.local_s:g} {unit})", result.local),
        (f"revisit (>= {result.local_s:g} {unit})", result.revisit),
    ):
        if stats.count:
            trans = f"{stats.trans_mean_m:.3f} ± {stats.trans_std_m:.3f}"
            rot = f"{stats.rot_mean_deg:.2f} ± {stats.rot_std_deg:.2f}"
            lines.append(f"{name:<22} {stats.count:>6} {trans:>17} {stats.trans_max_m:>7.3f} {rot:>15}")
        else:
            lines.append(f"{name:<22} {0:>6} {'-':>17} {'-':>7} {'-':>15}")
    return "\n".join(lines) + "\n"


def align_se2(est: Sequence[Sequence[float]], ref: Sequence[Sequence[float]]) -> Pose:
    """The SE(2) transform (x, y, theta) taking ``est``'s positions onto ``ref``'s, pair by pair, in
    the least-squares sense (Umeyama's method without scale): the alignment before an ATE, or to put a
    map built in its own frame onto the site's."""
    a = np.array([p[:2] for p in est], dtype=np.float64)
    b = np.array([p[:2] for p in ref], dtype=np.float64)
    if a.shape != b.shape or len(a) == 0:
        raise ValueError(f"need as many poses on both sides and at least one, got {len(a)} and {len(b)}")
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ma).T @ (b - mb)
    th = math.atan2(float(h[0, 1] - h[1, 0]), float(h[0, 0] + h[1, 1]))
    c, s = math.cos(th), math.sin(th)
    t = mb - np.array([[c, -s], [s, c]]) @ ma
    return float(t[0]), float(t[1]), th


def transform_xy(tf: Sequence[float], xy: FloatArray) -> FloatArray:
    """Points (N, 2) moved by the SE(2) transform ``tf`` (x, y, theta)."""
    c, s = math.cos(tf[2]), math.sin(tf[2])
    return np.column_stack((tf[0] + c * xy[:, 0] - s * xy[:, 1], tf[1] + s * xy[:, 0] + c * xy[:, 1]))
