"""The fleet map: the robots' maps, piece by piece, registered to one another where they see the
same place, placed in the site frame by one pose graph, and merged into one map. Pure.

Each robot builds its map in the site frame (its keeper restarts the map once UWB fixes place the
robot), but only as well as the fused pose placed its first turns: on the apartment two robots'
maps were measured 0.16 m and 1.5 degrees apart, and the console's overlay draws every wall twice.
And a map can be bent along the way (a drift its own graph never closed), which no rigid correction
of the whole map undoes.

``FleetMap.put(robot, RobotMap)`` takes a robot's latest map, with its submaps if it shares them;
``build()`` returns the fleet map:

1. **Pieces.** A robot's pieces are its submaps (cells in each one's frame, and where its optimised
   graph puts that frame), or its whole map as one piece (``WHOLE``) in a frame at its centre. The
   target the others' pieces are matched onto is its map: drawn from its submaps at the poses given
   with them, or as shared. Its likelihood field is a Gaussian of the distance to its nearest wall
   (sd ``field_sigma_m``), zero where the map knows nothing; a piece's points are its walls (at most
   ``max_points``, evenly subsampled).
2. **Inter-robot closures.** Each piece of one robot is matched onto every other robot's map: its
   walls on that map's known floor (grown by the window) are searched by branch and bound
   (``bnb.search``, Hess et al. 2016) within ``window_xy_m`` / ``window_theta_rad`` of where its robot
   put it, then refined on the interpolated field; kept when the overlap holds at least
   ``min_overlap_points`` walls and the score reaches ``min_score``, and tied to the other robot's
   piece whose walls hold most of the matched walls. A match stands while both pieces keep their
   versions; a refused one is tried again once the other map changed (``retry_builds``); a build
   searches at most ``max_searches_per_build`` (``pending``: what it left for the next).
3. **The site frame.** A pose graph (``posegraph.PoseGraph``): node 0 is the site frame, held
   still; each piece a node where its robot put it, tied there by its robot's placement
   (``placement_sigma``, what UWB placement is good for, shared among the robot's pieces), to the
   robot's next piece by their relative pose (``chain_sigma``), and to other robots' pieces by each
   match (``registration_sigma``; half where an overlap is matched both ways): solved as plain least
   squares, then again Cauchy-robust from there when there is more than one match (only then can a
   false closure disagree with the others). Maps that overlap nobody stay where their robots put
   them; a pair pulls both halfway, weighted by the priors.
4. **Merge.** Each piece is resampled (nearest cell) at its solved pose onto one lattice of
   ``resolution_m``; a cell is a wall where at least one piece sees a wall and at least as many see
   a wall as see free floor, free where more see floor, unknown where none knows it.

A robot that maps in its own frame (no UWB: ``RobotMap.site_frame`` false) has no placement to go
on: the fleet map's frame is the site frame if any robot is in it, else the own frame of the robot
first in name order (whatever order the maps came in), and
every other robot is found on the maps already placed by a global search (``_global_match``: every
heading, anywhere, verified both ways at full resolution, refused when two places fit about as
well), then taken as placed there (``FleetResult.frames``), and searched for again as its map
grows (moved if the search then puts it beyond a registration's window); until found it is left out
(``FleetResult.unframed``).

The fleet map's version counts builds whose cells changed. Time is not needed; no I/O.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.bnb import PrecomputedGrids, search
from fleetlink.agent.mapping.posegraph import PoseGraph
from fleetlink.shared.se2 import Pose, apart, compose, inverse, relative

__all__ = ["FleetMap", "FleetMapConfig", "FleetResult", "Registration", "RobotMap", "Submap"]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I8 = npt.NDArray[np.int8]

WALL = 100
FREE = 0
UNKNOWN = -1


@dataclass(frozen=True, slots=True)
class FleetMapConfig:
    resolution_m: float = 0.05
    """The fleet map's cell size (the onboard maps' own)."""
    field_sigma_m: float = 0.05
    """Spread of each map's likelihood field about its walls."""
    window_xy_m: float = 0.5
    """How far a map may be from where its robot placed it (UWB placement, a few decimetres)."""
    window_theta_rad: float = math.radians(5.0)
    angle_step_rad: float = math.radians(0.25)
    """The search's angle step; the answer is refined below it."""
    min_score: float = 0.7
    """Mean field value under the overlapping walls a registration must reach (1: every wall on a
    wall). Measured: true overlaps of two onboard maps of the apartment score 0.77-0.93; a map
    turned 90 degrees onto a plan of the same rooms 0.57."""
    min_overlap_points: int = 200
    """Walls of one map on the other's known floor a registration needs (200 cells: 10 m of wall)."""
    max_points: int = 4000
    """Walls per map used for registration (evenly subsampled beyond this)."""
    placement_sigma_xy_m: float = 0.15
    placement_sigma_theta_rad: float = math.radians(2.0)
    registration_sigma_xy_m: float = 0.02
    registration_sigma_theta_rad: float = math.radians(0.3)
    chain_sigma_xy_m: float = 0.10
    chain_sigma_theta_rad: float = math.radians(2.0)
    """How far one submap may move against the next of the same robot: what its own graph is good for
    between two submaps a few metres apart (its relations: a few centimetres, tenths of a degree)."""
    max_searches_per_build: int = 32
    """Registrations searched per build at most (~25 ms each): a build's cost stays bounded however
    many submaps arrive at once (a console that joins late catches up over a few builds)."""
    retry_builds: int = 5
    """A refused registration is tried again once the other map has changed, at most every this many
    builds (a piece that overlaps nothing yet would otherwise be searched at every build)."""
    global_resolution_m: float = 0.2
    """The cells of the global search that finds a map in its own frame on the others' (every
    heading, anywhere on them); its answer is then searched again at ``resolution_m``."""
    global_angle_step_rad: float = math.radians(1.0)
    global_points: int = 1500
    """Walls of the map searched for, at ``global_resolution_m`` (evenly subsampled beyond this)."""
    global_min_overlap_points: int = 400
    """Walls (at ``resolution_m``) a map in its own frame must lay on another's known floor to be
    placed by the global search: twice a local registration's, since nothing bounds where it may
    fit (20 m of wall)."""

    def __post_init__(self) -> None:
        for name in (
            "resolution_m", "field_sigma_m", "window_xy_m", "window_theta_rad", "angle_step_rad",
            "placement_sigma_xy_m", "placement_sigma_theta_rad", "registration_sigma_xy_m",
            "registration_sigma_theta_rad", "chain_sigma_xy_m", "chain_sigma_theta_rad",
            "global_resolution_m", "global_angle_step_rad",
        ):  # fmt: skip
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"fleet map: {name} must be a finite number > 0, got {v!r}")
        if not 0 < self.min_score <= 1:
            raise ValueError(f"fleet map: min_score must be in (0, 1], got {self.min_score!r}")
        if self.max_searches_per_build < 1 or self.retry_builds < 1:
            raise ValueError("fleet map: max_searches_per_build and retry_builds must be >= 1")
        if self.min_overlap_points < 1 or self.max_points < self.min_overlap_points:
            raise ValueError("fleet map: need 1 <= min_overlap_points <= max_points")
        if self.global_points < 1 or self.global_min_overlap_points < 1:
            raise ValueError("fleet map: global_points and global_min_overlap_points must be >= 1")


@dataclass(frozen=True, slots=True)
class Submap:
    """One piece of a robot's map as its pose graph has it: the cells its nodes drew, in the frame of
    its first node, and where the robot's optimised graph puts that frame in its map frame (the site
    frame once UWB placed the robot). Cells -1 unknown, 0 free, 100 occupied, row 0 at the bottom."""

    index: int
    version: int
    """Changes each time it is drawn again (on a robot: the nodes drawn into it; the open submap's grows)."""
    pose: Pose
    cells: I8
    resolution: float
    origin: tuple[float, float]
    """The lower-left corner of cell (0, 0) in the submap's own frame."""

    def __post_init__(self) -> None:
        if self.index < 0 or self.version < 0:
            raise ValueError(f"submap: index and version must be >= 0, got {self.index}, {self.version}")
        if len(self.pose) != 3 or not all(math.isfinite(v) for v in self.pose):
            raise ValueError(f"submap {self.index}: pose must be three finite numbers, got {self.pose!r}")
        _check_cells(self.cells, self.resolution, self.origin, f"submap {self.index}")


@dataclass(frozen=True, slots=True)
class RobotMap:
    """One robot's map as it shares it: cells -1 unknown, 0 free, 100 occupied (row 0 at the bottom),
    and the submaps it was drawn from, if the robot shares them (``submaps``, in index order). A map
    without submaps is placed and merged as one rigid piece."""

    cells: I8
    resolution: float
    origin: tuple[float, float]
    version: int
    submaps: tuple[Submap, ...] = ()
    site_frame: bool = True
    """The map is in the site (UWB) frame. False: in its own frame (a robot without UWB; its map
    begins where it started), which the fleet map finds on the others' maps (``FleetResult.frames``)."""

    def __post_init__(self) -> None:
        _check_cells(self.cells, self.resolution, self.origin, "robot map")
        indices = [s.index for s in self.submaps]
        if indices != sorted(set(indices)):
            raise ValueError("robot map: submaps must come in increasing index order, each once")


def _check_cells(cells: I8, resolution: float, origin: tuple[float, float], what: str) -> None:
    if cells.ndim != 2 or cells.size == 0:
        raise ValueError(f"{what}: cells must be a non-empty 2D array")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"{what}: resolution must be a finite number > 0, got {resolution!r}")
    if not all(math.isfinite(v) for v in origin):
        raise ValueError(f"{what}: origin must be finite, got {origin!r}")


@dataclass(frozen=True, slots=True)
class Registration:
    """Robot ``b``'s piece ``b_piece`` seen from the frame of robot ``a``'s piece ``a_piece``, as
    matching the first onto ``a``'s map measured it (a map shared whole is its robot's piece
    ``WHOLE``, -1)."""

    a: str
    b: str
    z: Pose
    score: float
    points: int
    a_piece: int = -1
    b_piece: int = -1


@dataclass(frozen=True, slots=True)
class FleetResult:
    cells: I8
    resolution: float
    origin: tuple[float, float]
    version: int
    corrections: dict[str, Pose]
    """Per robot: the rigid motion (site frame) applied to its map; for a map of several submaps,
    the mean of its pieces' (``piece_corrections``)."""
    registrations: tuple[Registration, ...]
    piece_corrections: dict[str, dict[int, Pose]] = field(default_factory=dict)
    """Per robot, per piece index: the rigid motion applied to that piece."""
    frames: dict[str, Pose] = field(default_factory=dict)
    """Per robot whose map is in its own frame and was found on the others': where that frame lies
    in the fleet map's (its ``corrections``): a pose the robot reports, composed onto this, is on
    the fleet map. The fleet map's frame is the site frame, or with no robot in it, the own frame
    of the robot first in name order."""
    unframed: tuple[str, ...] = ()
    """Robots in their own frames not (yet) found on the others' maps: left out of the fleet map."""


@dataclass
class _Piece:
    index: int
    version: int
    placed: Pose
    """Its frame in the site frame, as its robot placed it."""
    cells: I8
    resolution: float
    origin: tuple[float, float]
    local: F64
    """Its walls in its own frame, at most ``max_points``."""


@dataclass
class _Prepared:
    map: RobotMap
    epoch: int
    """+1 when a robot's versions start again (a restarted agent): registrations are keyed on it."""
    cells: I8
    """What the others' pieces are matched onto: the map drawn from its pieces where its robot put
    them (so the match and the poses it is tied to are of one moment), or the map as shared."""
    origin: tuple[float, float]
    grids: PrecomputedGrids
    near_known: npt.NDArray[np.bool_]
    """The cells known, grown by the search window: where another's walls may be matched."""
    pieces: list[_Piece]
    signature: tuple[object, ...]
    """What was put: a map of the same signature again changes nothing."""


_RegKey = tuple[str, int, str, int, int, int]
"""(a, a's epoch, b, b's epoch, b's piece index, its version)."""

WHOLE = -1
"""The piece index of a map shared whole (submaps count from 0)."""


class _Placed(NamedTuple):
    """A robot in its own frame, placed by the global search."""

    epoch: int
    """Its map's epoch when placed (a restarted agent's new map is not placed by this)."""
    frame: Pose
    """Where its map frame lies in the fleet map's frame."""
    on: str
    """The robot on whose map it was found ..."""
    on_epoch: int
    """... and that map's epoch (robots found on it move and are left out with it)."""


class _Pending(NamedTuple):
    """A place the global search found for a robot not yet placed, in the slack below ``min_score``:
    taken once a search of the robot's next map version puts it there again."""

    epoch: int
    """The robot's map's epoch."""
    on: str
    """The robot on whose map it was found ..."""
    on_epoch: int
    """... and that map's epoch."""
    version: int
    """The robot's map's version then (searched again once it has changed)."""
    found: Pose
    """Where the robot's frame lies on that map."""


@dataclass
class FleetMap:
    config: FleetMapConfig = field(default_factory=FleetMapConfig)
    maps: dict[str, _Prepared] = field(default_factory=dict)
    refused: int = 0
    """Registrations tried and refused (too little overlap, too low a score)."""
    _regs: dict[_RegKey, tuple[Registration | None, int, int, int]] = field(default_factory=dict)
    """Per piece matched onto a map: the answer, that map's version then, the build it was made in,
    and the version of the other's piece it is tied to."""
    _builds: int = 0
    pending: int = 0
    """Searches the last build left for later (over its budget): build again, even if nothing changed."""
    _epochs: dict[str, int] = field(default_factory=dict)
    _version: int = 0
    _last: FleetResult | None = None
    _frames: dict[str, _Placed] = field(default_factory=dict)
    """Per robot in its own frame that the global search placed: where its frame lies in the fleet
    map's frame, and on which map (robot and epoch) it was found."""
    _pending: dict[str, _Pending] = field(default_factory=dict)
    """Per robot not yet placed: a place to be confirmed by a search of its map's next version."""
    _checked: dict[str, tuple[int, int]] = field(default_factory=dict)
    """Per robot placed by the global search: its map's version and the build when last searched."""
    _moving: dict[str, tuple[int, Pose]] = field(default_factory=dict)
    """Per robot placed by the global search: another place a search of its grown map found in the
    slack below ``min_score`` (the epoch of the map it was found on, where its frame lies on that
    map), to be confirmed by the next search before it is moved there."""
    _reference: tuple[str, ...] = ()
    """The robots whose frame is the fleet map's: those in the site frame, or the first by name."""
    global_why: dict[str, str] = field(default_factory=dict)
    """Per robot in its own frame: what its last global search found (a console's log says why a
    robot is not on the fleet map yet)."""
    _global_tried: dict[tuple[str, int, str, int], tuple[int, int, int]] = field(default_factory=dict)
    """(b, its epoch, a, its epoch) -> a refused global search of b's map onto a's: both versions
    then and the build."""
    _drawn: dict[str, DrawCache] = field(default_factory=dict)
    """Per robot: its pieces as its map was last drawn from them (``put``)."""
    _drawn_fleet: DrawCache = field(default_factory=dict)
    """The pieces as the fleet map was last drawn from them (``build``)."""

    def put(self, robot: str, m: RobotMap) -> bool:
        """Take ``robot``'s map (a newer version replaces the old). False: nothing new, or no walls
        yet. ValueError for submaps that would draw a map over ``MAX_CELLS``."""
        old = self.maps.get(robot)
        signature = (m.version, m.cells.shape, tuple((s.index, s.version, s.pose) for s in m.submaps))
        if old is not None and old.signature == signature:
            return False
        cfg = self.config
        pieces = _pieces(m, cfg.max_points)
        if not any(len(p.local) for p in pieces):
            return False
        if old is not None and (
            m.version < old.map.version
            or (m.version == old.map.version and not m.submaps and not old.map.submaps)
            or m.site_frame != old.map.site_frame
        ):
            # Versions that go back, or a whole map of the same version that is not the same map:
            # a restarted agent, whose pieces' (index, version) mean other pieces now.
            self._epochs[robot] = self._epochs.get(robot, 0) + 1
        if m.submaps:
            # Drawn from its pieces at the poses given with them: a match onto it is then tied to
            # those poses, not to a shared map of another moment (a closure solved in between).
            cache = self._drawn.setdefault(robot, {})
            cells, origin = _draw([(p, p.placed) for p in pieces], m.resolution, m.origin, cache)
        else:
            self._drawn.pop(robot, None)  # a whole map: no pieces to keep drawn
            cells, origin = m.cells, m.origin
        known = cells != UNKNOWN
        reach = math.ceil(cfg.window_xy_m / m.resolution)
        from scipy import ndimage  # here, not at import: agents import this module for ``Submap``

        near_known = ndimage.binary_dilation(known, iterations=reach) if reach else known
        grids = _field_grids(cells, m.resolution, origin, cfg.field_sigma_m)
        self.maps[robot] = _Prepared(m, self._epochs.get(robot, 0), cells, origin, grids, near_known, pieces, signature)
        return True

    def forget(self, robot: str) -> None:
        """Let ``robot``'s map go (gone, or begun again: what was registered of it no longer holds)."""
        self._drawn.pop(robot, None)
        if self.maps.pop(robot, None) is not None:
            self._epochs[robot] = self._epochs.get(robot, 0) + 1

    def build(self) -> FleetResult | None:
        """The fleet map from the maps held (None: none yet). Deterministic for the same maps taken in
        the same order. ValueError for maps placed so far apart that the fleet map would hold more
        than ``MAX_CELLS`` cells."""
        if not self.maps:
            return None
        self._builds += 1
        budget = [self.config.max_searches_per_build]
        robots = self._framed(budget)
        unframed = tuple(r for r in sorted(self.maps) if r not in robots)
        if not robots:
            return None
        regs: list[Registration] = []
        used: set[_RegKey] = set()
        for i, a in enumerate(robots):
            for b in robots[i + 1 :]:
                # b's pieces onto a's map; and a's onto b's, unless both are single pieces (the same
                # overlap measured twice).
                pairs = [(a, b)]
                if len(self.maps[a].pieces) > 1 or len(self.maps[b].pieces) > 1:
                    pairs.append((b, a))
                for x, y in pairs:
                    for piece in self.maps[y].pieces:
                        reg = self._register(x, y, piece, used, budget)
                        if reg is not None:
                            regs.append(reg)
        self._regs = {k: v for k, v in self._regs.items() if k in used}
        self.pending = -budget[0] if budget[0] < 0 else 0
        solved = self._solve(robots, regs)
        piece_corrections = {
            r: {p.index: compose(solved[(r, p.index)], inverse(p.placed)) for p in self.maps[r].pieces} for r in robots
        }
        corrections = {r: _mean_pose(list(piece_corrections[r].values())) for r in robots}
        frames = {r: corrections[r] for r in robots if not self.maps[r].map.site_frame}
        # On the first map's lattice (the onboard maps share one): resampling a map onto its own
        # lattice moves no wall by half a cell.
        first = self.maps[robots[0]].map
        placed = [(p, solved[(r, p.index)]) for r in robots for p in self.maps[r].pieces]
        cells, origin = _draw(placed, self.config.resolution_m, first.origin, self._drawn_fleet)
        last = self._last
        if (
            last is None
            or last.cells.shape != cells.shape
            or last.origin != origin
            or not np.array_equal(last.cells, cells)
        ):
            self._version += 1
        res = self.config.resolution_m
        self._last = FleetResult(
            cells, res, origin, self._version, corrections, tuple(regs), piece_corrections, frames, unframed
        )
        return self._last

    # -- maps in their own frames ----------------------------------------------------------------

    def _frame(self, robot: str) -> Pose:
        """Where ``robot``'s map frame lies in the fleet map's frame (identity for the reference)."""
        held = self._frames.get(robot)
        return held.frame if held is not None else (0.0, 0.0, 0.0)

    def _framed(self, budget: list[int]) -> list[str]:
        """The robots whose maps can be placed in the fleet map's frame, sorted: those in the site
        frame; with none, the robot first in name order (whichever map came first: a console's view
        the same every time), whose own frame becomes the fleet map's; and each
        robot in its own frame whose map the global search found on one of theirs (once found, kept
        while its map is of the same epoch and the reference is the same)."""
        site = tuple(sorted(r for r, p in self.maps.items() if p.map.site_frame))
        reference = site or (min(self.maps),)
        if reference != self._reference:
            self._reference, self._frames, self._checked, self._pending = reference, {}, {}, {}
            self._moving = {}
        framed = set(reference)
        for r, placed in list(self._frames.items()):
            if r in self.maps and self.maps[r].epoch == placed.epoch:
                framed.add(r)
            else:
                # Gone or begun again. The robots found on its map keep their frames: each was placed
                # in the fleet map's frame through where its map then lay, and that still holds.
                del self._frames[r]
                self._checked.pop(r, None)
        self._moving = {r: v for r, v in self._moving.items() if r in self._frames}
        for b in sorted(self._frames):
            if b in self._frames:  # not left out with the map it was found on
                self._search_again(b, framed, budget)
        for b in sorted(set(self.maps) - framed):
            for a in sorted(framed):
                frame = self._place_globally(b, a, budget)
                if frame is not None:
                    self._frames[b] = _Placed(self.maps[b].epoch, frame, a, self.maps[a].epoch)
                    self._checked[b] = (self.maps[b].map.version, self._builds)
                    framed.add(b)
                    break
        live = {(b, self.maps[b].epoch) for b in self.maps}
        self._pending = {b: v for b, v in self._pending.items() if (b, v.epoch) in live and b not in framed}
        self._global_tried = {k: v for k, v in self._global_tried.items() if (k[0], k[1]) in live}
        return sorted(framed)

    def _search_again(self, b: str, framed: set[str], budget: list[int]) -> None:
        """``b``'s map, placed by the global search, searched for again on the map it was found on
        once its map has changed, at most every ``retry_builds`` builds: moved where the search now
        puts it if that is further than a registration's window reaches; where the search places it
        nowhere and it no longer fits where it is as a placement must, left out (``framed`` loses
        it) until a search finds it again. A young map (a robot's first turn after its agent
        restarted) can fit a wrong place better than its right one, and a frame once placed is
        otherwise kept while its map lasts (measured in the real-time field: a map 4 s old placed
        0.6 m and 46 degrees off, at 0.57; the same robot's older map fitted where it belonged at
        0.67). (Where the robot it was found on has begun again, on that robot's new map.)"""
        cfg = self.config
        placed = self._frames[b]
        a = placed.on
        version, built = self._checked.get(b, (-1, -(10**9)))
        pb = self.maps[b]
        if a not in framed or a == b or pb.map.version == version or self._builds - built < cfg.retry_builds:
            return
        budget[0] -= 4
        if budget[0] < 0:
            return
        self._checked[b] = (pb.map.version, self._builds)
        pa = self.maps[a]
        self._frames[b] = placed = placed._replace(on_epoch=pa.epoch)  # searched on its map as it is now
        found, why, score = _global_match(pa, pb, cfg)
        moving = self._moving.pop(b, None)
        if found is not None:
            again = compose(self._frame(a), found)
            if not apart(again, placed.frame, cfg.window_xy_m, cfg.window_theta_rad):
                return
            # Moved as a first place is taken: at min_score, or in the slack below it once the
            # next search puts it there again (on the same map: where it lies in the fleet map's
            # frame may have moved).
            if score >= cfg.min_score or (
                moving is not None
                and moving[0] == pa.epoch
                and not apart(found, moving[1], cfg.window_xy_m, cfg.window_theta_rad)
            ):
                self._move(b, again)
                self.global_why[b] = f"on {a}'s map again: {why}"
                return
            self._moving[b] = (pa.epoch, found)
            why = f"elsewhere, {why}; to be confirmed as its map grows"
            self.global_why[b] = f"on {a}'s map: {why}"
        # No place fits it as the search asks now (or one to be confirmed): kept where it is if it
        # still fits there, else left out and searched for as a map not yet found.
        fits, there = _still_fits(pa, pb, compose(inverse(self._frame(a)), placed.frame), cfg)
        if not fits:
            self._leave_out(b, framed, f"on {a}'s map: no longer where it was placed ({there}); {why}")
            # Just searched: not again in this build.
            self._global_tried[(b, placed.epoch, a, pa.epoch)] = (pb.map.version, pa.map.version, self._builds)
            if found is not None:  # the place found, confirmed or not by the next search
                self._pending[b] = _Pending(placed.epoch, a, pa.epoch, pb.map.version, found)
        elif found is None:
            self.global_why[b] = f"on {a}'s map: still where it was placed ({there}); {why}"

    def _move(self, b: str, to: Pose, moved: set[str] | None = None) -> None:
        """``b``'s frame moved to ``to``, and with it the frames of the robots found on its map as it
        is (placed through where that map lay, they lie as far from it as before; not those found on
        an earlier map of a robot begun again). Each once: robots can be found on each other's maps
        (b on c's after c was found on b's old map, then searched again on its new one)."""
        moved = set() if moved is None else moved
        moved.add(b)
        placed = self._frames[b]
        self._frames[b] = placed._replace(frame=to)
        step = compose(to, inverse(placed.frame))
        for c, other in sorted(self._frames.items()):
            if other.on == b and other.on_epoch == placed.epoch and c not in moved:
                self._move(c, compose(step, other.frame), moved)

    def _leave_out(self, b: str, framed: set[str], why: str) -> None:
        """``b``'s frame given up, and those of the robots found on its map as it is (placed through
        where it no longer lies): each searched for again as a map not yet found."""
        placed = self._frames.pop(b, None)
        if placed is None:
            return
        self._checked.pop(b, None)
        self._moving.pop(b, None)
        framed.discard(b)
        self.global_why[b] = why
        for c, other in sorted(self._frames.items()):
            if other.on == b and other.on_epoch == placed.epoch:
                self._leave_out(c, framed, f"on {b}'s map, which was left out: {why}")

    def _place_globally(self, b: str, a: str, budget: list[int]) -> Pose | None:
        """Where ``b``'s map frame lies in the fleet map's frame, found by matching its map onto
        ``a``'s at every heading and anywhere over it (coarse), then searched again and refined at
        full resolution; None when it does not lay ``global_min_overlap_points`` walls on ``a``'s
        known floor at ``min_score``. A refusal is tried again once either map has changed, at most
        every ``retry_builds`` builds; a search costs four of the build's budget."""
        cfg = self.config
        pa, pb = self.maps[a], self.maps[b]
        key = (b, pb.epoch, a, pa.epoch)
        tried = self._global_tried.get(key)
        if tried is not None and (
            (tried[0], tried[1]) == (pb.map.version, pa.map.version) or self._builds - tried[2] < cfg.retry_builds
        ):
            return None
        budget[0] -= 4
        if budget[0] < 0:
            return None
        pending = self._pending.get(b)
        if pending is not None and (pending.epoch, pending.on, pending.on_epoch) != (pb.epoch, a, pa.epoch):
            pending = None  # found on another map (or another epoch of either): not this search's to confirm
        if pending is not None and pending.version == pb.map.version:
            return None  # a place to be confirmed: searched again once b's map has changed
        found, why, score = _global_match(pa, pb, cfg)
        if found is None:
            if pending is not None:
                del self._pending[b]
            if b not in self._pending:  # else a place found on another map, which says more
                self.global_why[b] = f"on {a}'s map: {why}"
            self._global_tried[key] = (pb.map.version, pa.map.version, self._builds)
            return None
        self.global_why[b] = f"on {a}'s map: {why}"
        if score >= cfg.min_score:
            self._pending.pop(b, None)
            return compose(self._frame(a), found)
        # In the slack below min_score, where real-time maps' true places and young maps' false
        # ones both score: taken once a search of its grown map puts it there again.
        if pending is not None and not apart(found, pending.found, cfg.window_xy_m, cfg.window_theta_rad):
            del self._pending[b]
            return compose(self._frame(a), found)
        self._pending[b] = _Pending(pb.epoch, a, pa.epoch, pb.map.version, found)
        self.global_why[b] = f"on {a}'s map: {why}; to be confirmed as its map grows"
        return None

    # -- inter-robot closures --------------------------------------------------------------------

    def _register(self, a: str, b: str, piece: _Piece, used: set[_RegKey], budget: list[int]) -> Registration | None:
        """``b``'s ``piece`` matched onto ``a``'s map, from the cache where it still holds: a match
        stands while the piece and the piece of ``a`` it is tied to are as they were drawn; a refusal
        is tried again when ``a``'s map has changed (``retry_builds``), within the build's search
        budget."""
        pa, pb = self.maps[a], self.maps[b]
        key = (a, pa.epoch, b, pb.epoch, piece.index, piece.version)
        used.add(key)
        cached = self._regs.get(key)
        if cached is not None:
            reg, a_version, built, anchor_version = cached
            if reg is not None and any(p.index == reg.a_piece and p.version == anchor_version for p in pa.pieces):
                return reg
            if reg is None and (a_version == pa.map.version or self._builds - built < self.config.retry_builds):
                return None
        budget[0] -= 1
        if budget[0] < 0:
            return None  # over the budget: counted in ``pending``, searched at a later build
        found = self._search(a, pa, b, piece)
        if found is None:
            self.refused += 1
            self._regs[key] = (None, pa.map.version, self._builds, 0)
            return None
        reg, anchor_version = found
        self._regs[key] = (reg, pa.map.version, self._builds, anchor_version)
        return reg

    def _search(self, a: str, pa: _Prepared, b: str, piece: _Piece) -> tuple[Registration, int] | None:
        cfg = self.config
        if not len(piece.local):
            return None
        # The piece's walls on a's known floor (grown by the window): the only ones a can vouch for.
        res = pa.map.resolution
        guess = compose(inverse(self._frame(a)), compose(self._frame(b), piece.placed))  # in a's map frame
        on = _on_known(pa, _transform(guess, piece.local))
        if int(on.sum()) < cfg.min_overlap_points:
            return None
        local = piece.local[on]
        found = search(pa.grids, local, guess, cfg.window_xy_m, cfg.window_theta_rad, cfg.min_score, cfg.angle_step_rad)
        if found is None:
            return None
        pose, _ = _refine(pa.grids, local, found[0], res, cfg.angle_step_rad)
        score = _score(pa.grids, local, pose)
        if score < cfg.min_score:
            return None
        anchor = _anchor(pa.pieces, _transform(pose, local), pose)
        reg = Registration(a, b, relative(anchor.placed, pose), score, int(on.sum()), anchor.index, piece.index)
        return reg, anchor.version

    # -- the site frame --------------------------------------------------------------------------

    def _solve(self, robots: list[str], regs: list[Registration]) -> dict[tuple[str, int], Pose]:
        placed = {(r, p.index): compose(self._frame(r), p.placed) for r in robots for p in self.maps[r].pieces}
        if not regs:
            return placed
        cfg = self.config
        g = PoseGraph()
        site = g.add_node((0.0, 0.0, 0.0))
        index = {k: g.add_node(pose) for k, pose in placed.items()}
        base_prior = np.diag(
            [cfg.placement_sigma_xy_m**-2, cfg.placement_sigma_xy_m**-2, cfg.placement_sigma_theta_rad**-2]
        )
        chain = np.diag([cfg.chain_sigma_xy_m**-2, cfg.chain_sigma_xy_m**-2, cfg.chain_sigma_theta_rad**-2])
        tie = np.diag(
            [cfg.registration_sigma_xy_m**-2, cfg.registration_sigma_xy_m**-2, cfg.registration_sigma_theta_rad**-2]
        )
        # An overlap matched both ways (b's pieces onto a's map and a's onto b's) is measured twice
        # from the same walls: each match counts half.
        both = {(reg.a, reg.b) for reg in regs} & {(reg.b, reg.a) for reg in regs}

        def info(reg: Registration) -> npt.NDArray[np.float64]:
            return tie / 2 if (reg.a, reg.b) in both else tie

        def add_fixed(graph: PoseGraph) -> None:
            for r in robots:
                pieces = self.maps[r].pieces
                # One placement per robot, shared among its pieces: UWB placed the map, not each piece.
                prior = base_prior / len(pieces)
                for p in pieces:
                    graph.add_edge(site, index[(r, p.index)], placed[(r, p.index)], prior)
                for p, q in itertools.pairwise(pieces):
                    graph.add_edge(index[(r, p.index)], index[(r, q.index)], relative(p.placed, q.placed), chain)

        # First plain least squares, then robust from there: started where the robots put their
        # maps, a registration a few decimetres off is tens of sigmas off, and a Cauchy weight
        # would all but drop it (measured: a 0.45 m offset only a third corrected).
        add_fixed(g)
        for reg in regs:
            g.add_edge(index[(reg.a, reg.a_piece)], index[(reg.b, reg.b_piece)], reg.z, info(reg))
        g.optimize(fixed=site)
        if len(regs) > 1:  # a false closure can only disagree with others where maps form loops
            robust = PoseGraph()
            for pose in g.poses:
                robust.add_node(pose)
            add_fixed(robust)
            for reg in regs:
                robust.add_edge(index[(reg.a, reg.a_piece)], index[(reg.b, reg.b_piece)], reg.z, info(reg), robust=True)
            robust.optimize(fixed=site)
            g = robust
        return {k: g.poses[i] for k, i in index.items()}


MAX_CELLS = 16_000_000
"""The most cells a drawn map may hold (the wire's ``MAX_MAP_CELLS``: 200 m x 200 m at 5 cm)."""


_Drawn = tuple[I8, I8]
"""A piece resampled at one pose onto one lattice: its cells (held, so their ``id`` stays its own)
and, over its box's lattice cells, the piece's cell under each one's centre (unknown off the piece)."""
DrawCache = dict[tuple[int, float, tuple[float, float], Pose, float, tuple[float, float]], _Drawn]
"""``_draw``'s pieces as last resampled, by (``id`` of the cells, their resolution and origin, the
pose, the lattice's resolution and point). A piece's cells must not change in place once drawn
(nothing does: a robot's new map comes as new arrays)."""


def _draw(
    placed: list[tuple[_Piece, Pose]],
    res: float,
    lattice: tuple[float, float],
    cache: DrawCache | None = None,
) -> tuple[I8, tuple[float, float]]:
    """``placed`` pieces, each resampled (nearest cell) at its pose onto the lattice of cells of
    ``res`` through ``lattice``: a wall where at least one sees a wall and at least as many see a
    wall as see floor, floor where more see floor, unknown where none knows it.

    Each piece is resampled over the lattice cells its placed box covers, whatever else is drawn with
    it, so ``cache`` (the pieces as the last call with it resampled them) gives a piece at the same
    pose as it was: most of a fleet map's pieces stand still between two drawings, and the resampling
    was most of a drawing's cost. Left holding this call's pieces only. ValueError, before anything
    is resampled, for pieces that span more than ``MAX_CELLS``."""
    px, py = lattice
    spans = [_lattice_span(_placed_box(p, pose), res, lattice) for p, pose in placed]
    r0, c0 = min(s[0] for s in spans), min(s[1] for s in spans)
    h, w = max(s[2] for s in spans) - r0, max(s[3] for s in spans) - c0
    if w * h > MAX_CELLS:
        raise ValueError(f"the pieces span {w * res:.0f} x {h * res:.0f} m, over {MAX_CELLS} cells")
    walls = np.zeros((h, w), dtype=np.int16)
    free = np.zeros((h, w), dtype=np.int16)
    kept: DrawCache = {}
    for (p, pose), (r, c, r1, c1) in zip(placed, spans, strict=True):
        key = (id(p.cells), p.resolution, p.origin, pose, res, lattice)
        d = cache.get(key) if cache is not None else None
        if d is None:
            d = (p.cells, _resample(p, pose, (r, c, r1, c1), res, lattice))
        kept[key] = d
        src = d[1]
        walls[r - r0 : r1 - r0, c - c0 : c1 - c0] += src >= 65
        free[r - r0 : r1 - r0, c - c0 : c1 - c0] += (src >= 0) & (src <= 25)
    if cache is not None:
        cache.clear()
        cache.update(kept)
    out = np.full((h, w), UNKNOWN, dtype=np.int8)
    out[free > walls] = FREE
    out[(walls > 0) & (walls >= free)] = WALL
    return out, (float(px + c0 * res), float(py + r0 * res))


def _lattice_span(
    box: tuple[float, float, float, float], res: float, lattice: tuple[float, float]
) -> tuple[int, int, int, int]:
    """The lattice cells (first row, first column, end row, end column) that cover ``box``."""
    px, py = lattice
    c0, r0 = math.floor((box[0] - px) / res), math.floor((box[1] - py) / res)
    return r0, c0, max(r0, math.ceil((box[3] - py) / res)), max(c0, math.ceil((box[2] - px) / res))


def _resample(p: _Piece, pose: Pose, span: tuple[int, int, int, int], res: float, lattice: tuple[float, float]) -> I8:
    """``p`` at ``pose`` on the lattice cells ``span`` of ``res`` through ``lattice``: each cell takes
    the piece's cell under its centre."""
    px, py = lattice
    r0, c0, r1, c1 = span
    xs = px + (np.arange(c0, c1) + 0.5) * res
    ys = py + (np.arange(r0, r1) + 0.5) * res
    ix, iy, ith = inverse(pose)
    cs, sn = math.cos(ith), math.sin(ith)
    # The cell centres in the piece's frame, (ix + cs x) - sn y and (iy + sn x) + cs y, a column's
    # part and a row's part added: the same sums in the same order as over a meshgrid.
    sx = (ix + cs * xs)[None, :] - (sn * ys)[:, None]
    sy = (iy + sn * xs)[None, :] + (cs * ys)[:, None]
    sc = np.floor((sx - p.origin[0]) / p.resolution).astype(np.int64)
    sr = np.floor((sy - p.origin[1]) / p.resolution).astype(np.int64)
    mh, mw = p.cells.shape
    ok = (sr >= 0) & (sr < mh) & (sc >= 0) & (sc < mw)
    src = np.full(sc.shape, UNKNOWN, dtype=np.int8)
    src[ok] = p.cells[sr[ok], sc[ok]]
    return src


def _anchor(pieces: list[_Piece], matched: F64, pose: Pose) -> _Piece:
    """The piece a match onto its robot's map is tied to: the one whose own walls hold most of the
    matched walls (``matched``, in its robot's map frame), the one whose frame lies nearest the match
    on a tie. The match holds while that piece stays as drawn, whatever its robot's later closures
    do to the pieces elsewhere."""

    def held(p: _Piece) -> int:
        x, y, th = inverse(p.placed)
        c, s = math.cos(th), math.sin(th)
        lx = x + c * matched[:, 0] - s * matched[:, 1]
        ly = y + s * matched[:, 0] + c * matched[:, 1]
        col = np.floor((lx - p.origin[0]) / p.resolution).astype(np.int64)
        row = np.floor((ly - p.origin[1]) / p.resolution).astype(np.int64)
        h, w = p.cells.shape
        ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        return int(np.count_nonzero(p.cells[row[ok], col[ok]] >= 65))

    if len(pieces) == 1:
        return pieces[0]
    return min(pieces, key=lambda p: (-held(p), (p.placed[0] - pose[0]) ** 2 + (p.placed[1] - pose[1]) ** 2))


def _pieces(m: RobotMap, max_points: int) -> list[_Piece]:
    """The map's pieces: its submaps, or the whole map as one piece (``WHOLE``) in a frame at its centre."""
    if m.submaps:
        return [
            _Piece(
                s.index,
                s.version,
                s.pose,
                s.cells,
                s.resolution,
                s.origin,
                _wall_points(s.cells, s.resolution, s.origin, max_points),
            )
            for s in m.submaps
        ]
    h, w = m.cells.shape
    cx, cy = m.origin[0] + 0.5 * w * m.resolution, m.origin[1] + 0.5 * h * m.resolution
    origin = (m.origin[0] - cx, m.origin[1] - cy)
    local = _wall_points(m.cells, m.resolution, origin, max_points)
    return [_Piece(WHOLE, m.version, (cx, cy, 0.0), m.cells, m.resolution, origin, local)]


def _transform(pose: Pose, pts: F64) -> F64:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack((pose[0] + c * pts[:, 0] - s * pts[:, 1], pose[1] + s * pts[:, 0] + c * pts[:, 1]))


def _mean_pose(poses: list[Pose]) -> Pose:
    xs = [p[0] for p in poses]
    ys = [p[1] for p in poses]
    th = math.atan2(sum(math.sin(p[2]) for p in poses), sum(math.cos(p[2]) for p in poses))
    return (sum(xs) / len(xs), sum(ys) / len(ys), th)


def _wall_points(cells: I8, resolution: float, origin: tuple[float, float], max_points: int) -> F64:
    rows, cols = np.nonzero(cells >= 65)
    if len(rows) > max_points:  # evenly subsampled, deterministic
        keep = np.linspace(0, len(rows) - 1, max_points).round().astype(np.int64)
        rows, cols = rows[keep], cols[keep]
    return np.column_stack((origin[0] + (cols + 0.5) * resolution, origin[1] + (rows + 0.5) * resolution)).astype(
        np.float64
    )


def _field_grids(
    cells: I8, resolution: float, origin: tuple[float, float], sigma: float, depth: int = 4
) -> PrecomputedGrids:
    from scipy import ndimage

    d = ndimage.distance_transform_edt(cells < 65) * resolution
    lik = np.exp(-0.5 * (np.asarray(d, dtype=np.float64) / sigma) ** 2).astype(np.float32)
    lik[cells == UNKNOWN] = 0.0
    return PrecomputedGrids(lik, origin, resolution, depth=depth)


def _coarsen(cells: I8, k: int) -> I8:
    """``cells`` in blocks of ``k`` x ``k``: a wall where any is, unknown where all are, else free."""
    h, w = cells.shape
    padded = np.full((-(-h // k) * k, -(-w // k) * k), UNKNOWN, dtype=np.int8)
    padded[:h, :w] = cells
    blocks = padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k)
    out = np.full(blocks.shape[::2], FREE, dtype=np.int8)
    out[(blocks == UNKNOWN).all(axis=(1, 3))] = UNKNOWN
    out[(blocks >= 65).any(axis=(1, 3))] = WALL
    return out


def _global_match(pa: _Prepared, pb: _Prepared, cfg: FleetMapConfig) -> tuple[Pose | None, str, float]:
    """Where ``pb``'s map frame lies in ``pa``'s, with nothing to go on but the two maps (a robot
    without UWB maps in a frame that begins where it started).

    1. Coarse, everywhere: ``pb``'s walls at ``global_resolution_m``, turned by every
       ``global_angle_step_rad``, correlated with ``pa``'s field over every translation at once (one
       FFT per heading). The field is one coarse cell wide about ``pa``'s walls, zero where ``pa``
       knows nothing and -1/2 on its known floor away from walls: the sum counts walls matched less
       walls drawn across ``pa``'s floor, whatever part of ``pb`` overlaps.
    2. The best ``GLOBAL_CANDIDATES`` peaks (``PEAKS_PER_HEADING`` local maxima a heading) at least
       1 m or 10 degrees apart, each searched again within two coarse cells and angle steps at full
       resolution and refined, then scored both ways
       (``pb``'s walls on ``pa``'s field and ``pa``'s on ``pb``'s, each over the walls on the other's
       known floor): a floor of repeating rooms fits one room over as well one way, not both.
    3. The one that matches the most walls (field >= 1/2) both ways, less the walls it draws across
       the other's known floor away from its walls, is kept when those are at least
       ``GLOBAL_MIN_SHARE`` of both maps' walls, its mean field value is within
       ``GLOBAL_SCORE_SLACK`` of ``min_score``, and no other peak far from it matches
       ``GLOBAL_MARGIN`` as many at a mean within ``GLOBAL_MEAN_MARGIN`` of its own (two places fit
       about as well: wait for more of either map). The mean alone does not tell: in the exhibition
       hall, a map placed 25 m off, where a few of its walls lie on the other's known floor along
       one wall, scores 0.74 against 0.68-0.71 where it belongs, but matches 0.19 of the walls
       against 0.62. Two scouts 80 s in (one mapped the west, the other the east, between them the
       pillars' 10 m grid) are left apart."""
    from scipy import ndimage
    from scipy.fft import irfft2, next_fast_len, rfft2

    res = pa.map.resolution
    k = max(1, round(cfg.global_resolution_m / res))
    gres = res * k
    coarse = _coarsen(pa.cells, k)
    d = np.asarray(ndimage.distance_transform_edt(coarse < 65), dtype=np.float64) * gres
    lik = np.exp(-0.5 * (d / gres) ** 2)
    value = np.where(coarse == UNKNOWN, 0.0, lik - 0.5 * (1.0 - lik) * (coarse == FREE))
    pts = _wall_points(_coarsen(pb.cells, k), gres, pb.origin, cfg.global_points)
    if len(pts) * gres < cfg.global_min_overlap_points * res:
        return None, f"{len(pts) * gres / res:.0f} walls, fewer than the overlap needs", 0.0
    centre = pts.mean(axis=0)
    local = pts - centre
    reach = math.ceil(np.hypot(local[:, 0], local[:, 1]).max() / gres) + 1
    h, w = value.shape
    side = 2 * reach + 1
    shape = (next_fast_len(h + side - 1, real=True), next_fast_len(w + side - 1, real=True))
    spectrum = rfft2(value.astype(np.float32), shape)  # single precision: a third of the time
    thetas = np.arange(-math.pi, math.pi, cfg.global_angle_step_rad)
    spacing = math.ceil(1.0 / gres)  # peaks 1 m apart
    peaks: list[tuple[float, Pose]] = []
    for th in thetas:
        c, s = math.cos(th), math.sin(th)
        col = np.floor((c * local[:, 0] - s * local[:, 1]) / gres + 0.5).astype(np.int64) + reach
        row = np.floor((s * local[:, 0] + c * local[:, 1]) / gres + 0.5).astype(np.int64) + reach
        kernel = np.zeros((side, side), dtype=np.float32)
        np.add.at(kernel, (side - 1 - row, side - 1 - col), 1.0)  # flipped: a convolution correlates
        corr = irfft2(spectrum * rfft2(kernel, shape), shape)[: h + side - 1, : w + side - 1]
        # Each heading's best few peaks, each taken with the cells within 1 m of it (a repeating floor
        # fits in several places at once).
        for _ in range(PEAKS_PER_HEADING):
            i = int(np.argmax(corr))
            r, cc = divmod(i, corr.shape[1])
            v = float(corr[r, cc])
            if not v > 0:
                break
            corr[max(0, r - spacing) : r + spacing + 1, max(0, cc - spacing) : cc + spacing + 1] = -np.inf
            # corr[r, cc]: the walls' centroid on cell (r - reach, cc - reach) of pa's field.
            x = pa.origin[0] + (cc - (side - 1) + reach + 0.5) * gres
            y = pa.origin[1] + (r - (side - 1) + reach + 0.5) * gres
            peaks.append((v, compose((x, y, float(th)), (-float(centre[0]), -float(centre[1]), 0.0))))
    peaks.sort(key=lambda p: -p[0])
    chosen: list[Pose] = []
    for _, pose in peaks:
        if len(chosen) == GLOBAL_CANDIDATES:
            break
        if all(apart(pose, q, 1.0, math.radians(10.0)) for q in chosen):
            chosen.append(pose)
    walls_b = _wall_points(pb.cells, pb.map.resolution, pb.origin, cfg.max_points)
    walls_a = _wall_points(pa.cells, res, pa.origin, cfg.max_points)
    scored = [c for c in (_verify(pa, pb, guess, walls_a, walls_b, cfg) for guess in chosen) if c is not None]
    if not scored:
        return None, "no place overlaps enough of the other's known floor", 0.0
    support, score, pose = max(scored, key=lambda c: c[0])
    share = support / (len(walls_a) + len(walls_b))
    best = f"the best place matches {share:.2f} of the walls at {score:.2f}"
    if share < GLOBAL_MIN_SHARE or score < cfg.min_score - GLOBAL_SCORE_SLACK:
        return None, best, score
    rival = [
        (other, mean)
        for other, mean, q in scored
        if other > GLOBAL_MARGIN * support
        and mean > score - GLOBAL_MEAN_MARGIN
        and apart(pose, q, 1.0, math.radians(10.0))
    ]
    if rival:  # another place fits about as much of both maps as well: wait for more of either
        return None, f"{best}, another {rival[0][0] / support:.2f} as many at {rival[0][1]:.2f}", score
    return pose, best, score


def _verify(
    pa: _Prepared, pb: _Prepared, guess: Pose, walls_a: F64, walls_b: F64, cfg: FleetMapConfig
) -> tuple[int, float, Pose] | None:
    """``guess`` (``pb``'s frame in ``pa``'s) searched again within two coarse cells and angle steps at
    full resolution, refined, and scored both ways: the walls matched less those drawn across the
    other's known floor away from its walls, the lower mean field value of the two ways, the pose.
    None where too few walls overlap the other's known floor."""
    res = pa.map.resolution
    gres = res * max(1, round(cfg.global_resolution_m / res))
    on = _on_known(pa, _transform(guess, walls_b))
    if int(on.sum()) < cfg.global_min_overlap_points:
        return None
    fine = search(pa.grids, walls_b[on], guess, 2 * gres, 2 * cfg.global_angle_step_rad, 0.0, cfg.angle_step_rad)
    if fine is None:
        return None
    pose, _ = _refine(pa.grids, walls_b[on], fine[0], res, cfg.angle_step_rad)
    on = _on_known(pa, _transform(pose, walls_b))
    back = _on_known(pb, _transform(inverse(pose), walls_a))
    if int(on.sum()) < cfg.global_min_overlap_points or not back.any():
        return None
    there = _values(pa.grids, walls_b[on], pose)
    here = _values(pb.grids, walls_a[back], inverse(pose))
    # Walls matched, less walls drawn across the other's known floor away from its walls.
    crossing = _on_floor(pa, _transform(pose, walls_b[on]), there) + _on_floor(
        pb, _transform(inverse(pose), walls_a[back]), here
    )
    support = int(np.count_nonzero(there >= 0.5) + np.count_nonzero(here >= 0.5)) - crossing
    return support, min(float(there.mean()), float(here.mean())), pose


def _still_fits(pa: _Prepared, pb: _Prepared, guess: Pose, cfg: FleetMapConfig) -> tuple[bool, str]:
    """Whether ``pb``'s map still fits at ``guess`` (its frame in ``pa``'s) as well as the global
    search asks of a place it accepts, and the figures."""
    walls_b = _wall_points(pb.cells, pb.map.resolution, pb.origin, cfg.max_points)
    walls_a = _wall_points(pa.cells, pa.map.resolution, pa.origin, cfg.max_points)
    found = _verify(pa, pb, guess, walls_a, walls_b, cfg)
    if found is None:
        return False, "too little of it overlaps the other's known floor there"
    share = found[0] / (len(walls_a) + len(walls_b))
    fits = share >= GLOBAL_MIN_SHARE and found[1] >= cfg.min_score - GLOBAL_SCORE_SLACK
    return fits, f"it matches {share:.2f} of the walls there at {found[1]:.2f}"


GLOBAL_CANDIDATES = 32
"""Peaks of the coarse correlation verified at full resolution (each a few milliseconds)."""
PEAKS_PER_HEADING = 4
"""Local maxima taken from each heading's correlation (a hall's pillars in a grid fit in several
places at once)."""
GLOBAL_MIN_SHARE = 0.3
"""The share of both maps' walls (each at most ``max_points``) the best peak must match. Measured in
the exhibition hall: where the maps belong 0.62 of them; the best of the places they do not, 0.23
(their walls on the other's known floor there few, the mean under them as high as where they belong)."""
GLOBAL_SCORE_SLACK = 0.2
"""How far below ``min_score`` the best peak's mean field value may be (both ways): two maps of a
hall drawn by different robots, their far walls dotted where each one's beams fell, score 0.68-0.71
where they belong in lockstep, and 0.52-0.63 in real time on a loaded machine (its lidar turns
matched later, its maps thinner); the share of walls matched is what tells the places apart."""
GLOBAL_MARGIN = 0.8
"""The most walls matched (both ways) another peak far from the best may have, as a share of the
best's: more, and the two maps fit in two places about as well."""
GLOBAL_MEAN_MARGIN = 0.05
"""... and fits them about as well: its mean field value (both ways) within this of the best's. Two
identical rooms side by side fit a map of one of them at 0.882 each; with a 3 m partition in one, a
map of that room fits the other 0.78 against 0.88, matching 0.81 as many walls."""


def _on_floor(p: _Prepared, pts: F64, field: F64) -> int:
    """How many of ``pts`` (its map frame; ``field`` their values there) lie on ``p``'s known free
    floor, away from its walls (field < 0.05: over 12 cm off at 5 cm spread)."""
    return int(np.count_nonzero(_cells_at(p, p.cells == FREE, pts) & (field < 0.05)))


def _on_known(p: _Prepared, pts: F64) -> npt.NDArray[np.bool_]:
    """Which of ``pts`` (its map frame) lie on ``p``'s known floor, grown by the search window."""
    return _cells_at(p, p.near_known, pts)


def _cells_at(p: _Prepared, mask: npt.NDArray[np.bool_], pts: F64) -> npt.NDArray[np.bool_]:
    """``mask`` (on ``p``'s cells) under each of ``pts`` (its map frame); False off the map."""
    res = p.map.resolution
    c = np.floor((pts[:, 0] - p.origin[0]) / res).astype(np.int64)
    r = np.floor((pts[:, 1] - p.origin[1]) / res).astype(np.int64)
    h, w = mask.shape
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    out = np.zeros(len(c), dtype=bool)
    out[inside] = mask[r[inside], c[inside]]
    return out


def _score(grids: PrecomputedGrids, local: F64, pose: Pose) -> float:
    return float(_values(grids, local, pose).mean())


def _values(grids: PrecomputedGrids, local: F64, pose: Pose) -> F64:
    """The field under each of ``local`` placed at ``pose``."""
    values: F64 = _lookup(grids, local, pose[0], pose[1], np.array([pose[2]]))[0]
    return values


def _lookup(grids: PrecomputedGrids, local: F64, x: float, y: float, thetas: F64) -> F64:
    """Bilinear field values under ``local`` placed at (x, y, each theta): shape (len(thetas), N)."""
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    px, py = local[None, :, 0], local[None, :, 1]
    res, pad = grids.resolution, grids.pad
    u = (x + c * px - s * py - grids.origin[0]) / res - 0.5 + pad
    v = (y + s * px + c * py - grids.origin[1]) / res - 0.5 + pad
    base = grids.level(0)
    hh, ww = base.shape
    u = np.clip(u, 0, ww - 1.001)
    v = np.clip(v, 0, hh - 1.001)
    i, j = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - i, v - j
    f00, f01 = base[j, i], base[j, i + 1]
    f10, f11 = base[j + 1, i], base[j + 1, i + 1]
    out: F64 = (f00 * (1 - fu) + f01 * fu) * (1 - fv) + (f10 * (1 - fu) + f11 * fu) * fv
    return out


def _refine(grids: PrecomputedGrids, local: F64, pose: Pose, res: float, step: float) -> tuple[Pose, float]:
    """The search's answer refined below its lattice on the interpolated field: the best of a 5 x 5 x 5
    grid one lattice step around it, then of one a quarter as wide around that (deterministic, no
    derivatives needed; a tenth of the lookups of one fine grid over the whole step)."""
    best, best_score = pose, _score(grids, local, pose)
    for span_xy, span_th in ((res, step), (res / 4, step / 4)):
        centre = best
        thetas = centre[2] + np.linspace(-span_th, span_th, 5)
        for dx in np.linspace(-span_xy, span_xy, 5):
            for dy in np.linspace(-span_xy, span_xy, 5):
                scores = _lookup(grids, local, centre[0] + dx, centre[1] + dy, thetas).mean(axis=1)
                k = int(np.argmax(scores))
                if scores[k] > best_score:
                    best_score = float(scores[k])
                    best = (centre[0] + float(dx), centre[1] + float(dy), float(thetas[k]))
    return best, best_score


def _placed_box(p: _Piece, pose: Pose) -> tuple[float, float, float, float]:
    h, w = p.cells.shape
    xs = (p.origin[0], p.origin[0] + w * p.resolution)
    ys = (p.origin[1], p.origin[1] + h * p.resolution)
    pts = [compose(pose, (x, y, 0.0)) for x in xs for y in ys]
    return (min(q[0] for q in pts), min(q[1] for q in pts), max(q[0] for q in pts), max(q[1] for q in pts))
