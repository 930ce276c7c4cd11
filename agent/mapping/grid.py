"""A log-odds occupancy grid that grows as the robot explores, with vectorised ray updates.

The sweeping-robot seed's equations (7-11), the standard binary Bayes filter per cell:

    p(m | z_1:t) / (1 - p(m | z_1:t))  =  [p(m | z_t) / (1 - p(m | z_t))] * [p(m | z_1:t-1) / (1 - ...)] / [p0 / (1 - p0)]
    l_t = l_{t-1} + log(p(m | z_t) / (1 - p(m | z_t))) - l_0          with l = log(p / (1 - p))
    p   = 1 - 1 / (1 + exp(l))

where ``p(m | z_t)`` is the inverse sensor model: ``p_occ`` for the cell a beam ends in, ``p_free``
for the cells it passes through, and ``l_0 = log(p0 / (1 - p0))`` the prior (0 for p0 = 0.5).
Log-odds are clamped to ``[l_min, l_max]`` so a cell can still change its mind (a door opens).
Each cell is updated at most once per scan (a cell crossed by several beams counts once; a cell
that is both crossed and hit counts as hit).

Cells: ``grid[row, col]``, row 0 at the bottom (``y = origin_y``), like map_server. The frame is
the UWB frame (metres). The grid grows in chunks (``grow_step``) when a scan reaches beyond it;
``origin`` moves accordingly.

It also keeps the matcher's *likelihood field*: the occupied probability blurred by a small
binomial kernel (so scores and gradients are smooth), plus a max-pooled coarse copy for the
correlative search. Both are refreshed per scan only over small tiles around the cells whose
occupied evidence the scan changed (``_refresh_cells``), or over the box the scans touched when
refreshed late (``refresh_stale``): the same values either way.

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["Box", "GridConfig", "LogOddsGrid", "logit"]

FloatArray = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
Box = tuple[int, int, int, int]  # row0, col0, row1, col1 (exclusive)

_KERNEL = np.array([1.0, 4.0, 6.0, 4.0, 1.0], dtype=np.float32) / 16.0
_K = 2  # kernel half-width, cells


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass(frozen=True, slots=True)
class GridConfig:
    resolution: float = 0.05  # m per cell
    p_occ: float = 0.7  # inverse sensor model: cell where a beam ends
    p_free: float = 0.4  # cells a beam passes through
    p_prior: float = 0.5
    l_min: float = -2.0  # clamp (p ~ 0.12)
    l_max: float = 3.5  # clamp (p ~ 0.97)
    grow_step: float = 8.0  # m added on a side when the grid must grow
    coarse: int = 4  # cells per coarse cell (the correlative search's first level)

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        for name in ("p_occ", "p_free", "p_prior"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {v}")
        if not self.p_free < self.p_prior < self.p_occ:
            raise ValueError("need p_free < p_prior < p_occ")
        if not self.l_min < 0.0 < self.l_max:
            raise ValueError("need l_min < 0 < l_max")
        if self.coarse < 1 or self.grow_step <= 0:
            raise ValueError("coarse must be >= 1 and grow_step > 0")


class LogOddsGrid:
    """The map. ``integrate(pose, ranges, angles, hit)`` adds one scan; see the module docstring."""

    def __init__(self, config: GridConfig | None = None, origin: tuple[float, float] = (0.0, 0.0)) -> None:
        self.config = cfg = config or GridConfig()
        self.resolution = cfg.resolution
        self.l_occ = logit(cfg.p_occ) - logit(cfg.p_prior)
        self.l_free = logit(cfg.p_free) - logit(cfg.p_prior)
        c = cfg.coarse
        self.origin = (float(origin[0]), float(origin[1]))
        self.logodds: F32 = np.zeros((c, c), dtype=np.float32)
        self.seen = np.zeros((c, c), dtype=bool)
        self.field: F32 = np.zeros((c, c), dtype=np.float32)
        self.coarse_field: F32 = np.zeros((1, 1), dtype=np.float32)
        self._tag = np.zeros(c * c, dtype=np.uint8)
        self._placed = False  # the first scan places the grid (then it only grows)
        self.empty = True  # nothing integrated yet
        self.version = 0  # +1 per integrated scan
        self.dirty: Box | None = None  # cells changed since the last take_dirty()
        self.stale: Box | None = None  # cells whose likelihood field waits for refresh_stale()
        # ``occupancy``'s cells as last computed, and the box changed since (None: none changed); the
        # map is read every share period while a scan changes a small part of it.
        self._cells: npt.NDArray[np.int8] | None = None
        self._cells_stale: Box | None = None

    # -- geometry ------------------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.logodds.shape
        return int(h), int(w)

    def to_cell(self, xy: FloatArray) -> FloatArray:
        """World (N, 2) -> continuous (col, row) cell coordinates (cell centres at k + 0.5)."""
        out: FloatArray = (xy - np.asarray(self.origin)) / self.resolution
        return out

    def ensure(self, xmin: float, ymin: float, xmax: float, ymax: float) -> None:
        """Grow (in ``grow_step`` chunks, keeping a multiple of ``coarse`` cells) to cover the box."""
        cfg, res = self.config, self.resolution
        h, w = self.shape
        ox, oy = self.origin
        if self.empty and not self._placed:
            # First scan: centre the grid on it. Cell *centres* sit on round coordinates (multiples
            # of the resolution): a wall on a round coordinate (buildings, a UWB frame aligned with
            # them, the simulator's plans) then falls in the middle of a cell, so scans from either
            # side hit the same cell; on a cell edge it would be mapped half a cell towards whichever
            # side saw it, and the matcher would inherit that offset.
            pad = cfg.grow_step
            ox = math.floor((xmin - pad) / res) * res - res / 2.0
            oy = math.floor((ymin - pad) / res) * res - res / 2.0
            w0 = math.ceil((xmax + pad - ox) / res)
            h0 = math.ceil((ymax + pad - oy) / res)
            self._realloc(0, 0, h0, w0, ox, oy, fresh=True)
            self._placed = True
            return
        step = math.ceil(cfg.grow_step / res)
        add_l = step if xmin < ox else 0
        add_b = step if ymin < oy else 0
        add_r = step if xmax > ox + w * res else 0
        add_t = step if ymax > oy + h * res else 0
        while xmin < ox - add_l * res:
            add_l += step
        while ymin < oy - add_b * res:
            add_b += step
        while xmax > ox + (w + add_r) * res:
            add_r += step
        while ymax > oy + (h + add_t) * res:
            add_t += step
        if add_l or add_b or add_r or add_t:
            self._realloc(add_b, add_l, h + add_b + add_t, w + add_l + add_r, ox - add_l * res, oy - add_b * res)

    def _realloc(self, row0: int, col0: int, h: int, w: int, ox: float, oy: float, fresh: bool = False) -> None:
        c = self.config.coarse
        # Keep shapes a multiple of the coarse factor (pad on the top/right), offsets too.
        row0 += (-row0) % c
        col0 += (-col0) % c
        oy = self.origin[1] - row0 * self.resolution if not fresh else oy
        ox = self.origin[0] - col0 * self.resolution if not fresh else ox
        h = max(h, row0 + self.shape[0])
        w = max(w, col0 + self.shape[1])
        h += (-h) % c
        w += (-w) % c
        old_h, old_w = self.shape
        lo = np.zeros((h, w), dtype=np.float32)
        seen = np.zeros((h, w), dtype=bool)
        fld = np.zeros((h, w), dtype=np.float32)
        if not fresh:
            lo[row0 : row0 + old_h, col0 : col0 + old_w] = self.logodds
            seen[row0 : row0 + old_h, col0 : col0 + old_w] = self.seen
            fld[row0 : row0 + old_h, col0 : col0 + old_w] = self.field
            if self.dirty is not None:
                r0, c0, r1, c1 = self.dirty
                self.dirty = (r0 + row0, c0 + col0, r1 + row0, c1 + col0)
            if self.stale is not None:
                r0, c0, r1, c1 = self.stale
                self.stale = (r0 + row0, c0 + col0, r1 + row0, c1 + col0)
        self.logodds, self.seen, self.field = lo, seen, fld
        self._cells = None
        self.origin = (ox, oy)
        self.coarse_field = _max_pool(fld, c)
        self._tag = np.zeros(h * w, dtype=np.uint8)

    # -- updates -------------------------------------------------------------------------------

    def integrate(
        self,
        sensor_pose: tuple[float, float, float],
        ranges: FloatArray,
        angles: FloatArray,
        hit: npt.NDArray[np.bool_],
        *,
        refresh: bool = True,
    ) -> Box | None:
        """Add one scan taken from ``sensor_pose`` (x, y, theta of the sensor in the map frame).

        ``ranges``/``angles``: valid beams (see ``scan.prepare``); ``hit`` False for beams that
        returned nothing within range (they only clear). Returns the changed box of cells.
        ``refresh=False`` leaves the likelihood field for a later ``refresh_stale`` (a redraw of many
        scans, or a grid nobody matches against until it is read): the box is remembered in ``stale``.
        """
        if ranges.size == 0:
            return None
        sx, sy, sth = sensor_pose
        res = self.resolution
        world_a = angles + sth
        cos_a, sin_a = np.cos(world_a), np.sin(world_a)
        ex, ey = sx + ranges * cos_a, sy + ranges * sin_a
        # Keep a metre of empty cells around everything seen: the matcher reads past the edge as 0.
        self.ensure(
            min(float(ex.min()), sx) - 1.0, min(float(ey.min()), sy) - 1.0,
            max(float(ex.max()), sx) + 1.0, max(float(ey.max()), sy) + 1.0,
        )  # fmt: skip
        h, w = self.shape
        ox, oy = self.origin
        # Free samples: one per cell length along each beam, stopping short of the endpoint.
        counts = np.maximum((ranges / res - 0.5).astype(np.int64), 0)
        free_idx, box = _free_cells(sx, sy, cos_a, sin_a, counts, res, ox, oy, w)
        ocol = ((ex[hit] - ox) / res).astype(np.int64)
        orow = ((ey[hit] - oy) / res).astype(np.int64)
        occ_idx = orow * w + ocol
        # Every cell lies inside the grid (``ensure`` above), but clip the indices if some box says not.
        if box is not None and not (box[0] >= 0 and box[1] >= 0 and box[2] <= h and box[3] <= w):
            np.clip(free_idx, 0, h * w - 1, out=free_idx)
            self._cells = None  # a clipped index lands outside any box
        if orow.size and not (
            int(orow.min()) >= 0 and int(ocol.min()) >= 0 and int(orow.max()) < h and int(ocol.max()) < w
        ):
            np.clip(occ_idx, 0, h * w - 1, out=occ_idx)
            self._cells = None
        tag = self._tag
        tag[free_idx] = 1
        tag[occ_idx] = 2  # hit wins over crossed
        cells = np.concatenate((free_idx, occ_idx))
        delta = np.array([0.0, self.l_free, self.l_occ], dtype=np.float32).take(tag[cells])
        flat = self.logodds.reshape(-1)
        # Fancy-index assignment with repeated indices writes each cell once with the same value:
        # exactly one update per cell per scan, without sorting.
        old = flat[cells]
        new = np.clip(old + delta, self.config.l_min, self.config.l_max)
        flat[cells] = new
        tag[cells] = 0
        self.seen.reshape(-1)[cells] = True
        if orow.size:
            hits = (int(orow.min()), int(ocol.min()), int(orow.max()) + 1, int(ocol.max()) + 1)
            box = hits if box is None else _union(box, hits)
        if box is None:  # no beam reached past half a cell and none hit: nothing changed
            return None
        if refresh:
            # The field reads only the occupied evidence, which is 0 wherever the log-odds are <= 0:
            # of the ~10^5 cells a scan's rays cross, a few hundred change it (walls hit, walls
            # cleared). Recompute the field around those alone, unless older changes wait (stale).
            changed = cells[(new != old) & ((new > 0.0) | (old > 0.0))]
            if self.stale is not None or not self._refresh_cells(changed):
                self._refresh_field(box)
        else:
            self.stale = box if self.stale is None else _union(self.stale, box)
        self.empty = False
        self.version += 1
        self.dirty = box if self.dirty is None else _union(self.dirty, box)
        self._cells_stale = box if self._cells_stale is None else _union(self._cells_stale, box)
        return box

    def clear(self) -> None:
        """Forget every cell, keeping the grid's place and size (a redraw follows: the version goes on
        counting, and the whole grid is marked changed)."""
        self.logodds.fill(0.0)
        self.seen.fill(False)
        self.field.fill(0.0)
        self.coarse_field.fill(0.0)
        self.empty = True
        self.dirty = (0, 0, *self.shape)
        self.stale = None
        self._cells = None

    def blank_like(self) -> LogOddsGrid:
        """An empty grid in this one's place and size, its version going on from this one's: a grid to
        draw the same map again into, to take this one's place when drawn."""
        g = LogOddsGrid(self.config, self.origin)
        g._realloc(0, 0, *self.shape, *self.origin, fresh=True)
        g._placed = True
        g.version = self.version
        return g

    def refresh(self, box: Box | None = None) -> None:
        """Recompute the likelihood field over ``box`` (default: the whole grid, and nothing is stale)."""
        if box is None:
            self.stale = None
        self._refresh_field(box if box is not None else (0, 0, *self.shape))

    def refresh_stale(self) -> None:
        """Bring the likelihood field up to date over what ``integrate(refresh=False)`` changed: the
        same field, to the bit, as refreshing after every scan (each cell's value depends only on the
        log-odds around it)."""
        if self.stale is not None:
            box, self.stale = self.stale, None
            self._refresh_field(box)

    def _refresh_cells(self, changed: npt.NDArray[np.int64]) -> bool:
        """Recompute the likelihood field (and its coarse copy) over the small tiles within the kernel's
        reach of ``changed`` (flat indices, repeats allowed: the cells whose occupied evidence changed),
        with the same arithmetic in the same order as ``_refresh_field``: the same field, to the bit.
        False (nothing done) when a tile would reach past the grid's edge (the grid keeps a metre of
        empty cells around what it has seen, so that is the exception)."""
        if changed.size == 0:
            return True
        h, w = self.shape
        c = self.config.coarse
        t = c * -(-_TILE // c)  # tile side, a whole number of coarse cells (>= 2 * _K + 1)
        # A changed cell's 5 x 5 reach spans at most two tiles each way: those of its corners.
        corners = changed[None, :] + np.array([[-_K * w - _K], [-_K * w + _K], [_K * w - _K], [_K * w + _K]])
        rows, cols = np.divmod(corners, w)
        tw = -(-w // t)
        rows //= t
        cols //= t
        rows *= tw
        rows += cols
        tiles = _unique(rows.ravel())
        r0, c0 = np.divmod(tiles, tw)
        r0 *= t  # each tile's first row and column
        c0 *= t
        if int(r0[0]) < 2 * _K or int(r0[-1]) + t + 2 * _K > h:  # (sorted by row)
            return False
        if int(c0.min()) < 2 * _K or int(c0.max()) + t + 2 * _K > w:
            return False
        n = len(tiles)
        p = t + 2 * _K  # a tile with the kernel's reach around it
        span = np.arange(p, dtype=np.int64)
        patch = (span[:, None] * w + span[None, :]).ravel()
        # (rows, columns, tiles): every slice below runs along the tiles, contiguous.
        occ = self.logodds.reshape(-1).take(patch[:, None] + ((r0 - _K) * w + (c0 - _K))[None, :]).reshape(p, p, n)
        _evidence(occ, occ, self.l_occ)
        blur = _blur(occ, t, t)
        inner = (span[:t, None] * w + span[None, :t]).ravel()
        self.field.reshape(-1)[inner[:, None] + (r0 * w + c0)[None, :]] = blur.reshape(t * t, n)
        # The coarse cells of each tile: the maxima of its c x c blocks (element-wise maxima of strided
        # views, as _max_pool).
        k = t // c
        across = blur[:, 0::c].copy()
        for i in range(1, c):
            np.maximum(across, blur[:, i::c], out=across)
        pooled = across[0::c].copy()
        for i in range(1, c):
            np.maximum(pooled, across[i::c], out=pooled)
        cw = w // c
        cspan = np.arange(k, dtype=np.int64)
        cells = (cspan[:, None] * cw + cspan[None, :]).ravel()
        self.coarse_field.reshape(-1)[cells[:, None] + ((r0 // c) * cw + c0 // c)[None, :]] = pooled.reshape(k * k, n)
        return True

    def _refresh_field(self, box: Box) -> None:
        """Recompute the likelihood field (and its coarse copy) over ``box`` plus the kernel's reach."""
        h, w = self.shape
        c = self.config.coarse
        r0, c0, r1, c1 = box
        # The output region, grown by the kernel, aligned to coarse cells.
        orow0 = max(0, (r0 - _K) // c * c)
        ocol0 = max(0, (c0 - _K) // c * c)
        orow1 = min(h, -(-(r1 + _K) // c) * c)
        ocol1 = min(w, -(-(c1 + _K) // c) * c)
        # Input region: the output plus the kernel's half-width (zero outside the grid).
        irow0, icol0 = max(0, orow0 - _K), max(0, ocol0 - _K)
        irow1, icol1 = min(h, orow1 + _K), min(w, ocol1 + _K)
        lo = self.logodds[irow0:irow1, icol0:icol1]
        ih, iw = lo.shape
        # Occupied evidence in [0, 1]: 0 for free/unknown, rising with the log-odds above 0. Written into
        # a zero-padded buffer; every step below works in place (the same arithmetic, fewer temporaries).
        pad = np.zeros((ih + 2 * _K, iw + 2 * _K), dtype=np.float32)
        _evidence(lo, pad[_K : _K + ih, _K : _K + iw], self.l_occ)
        blur = _blur(pad, ih, iw)
        self.field[orow0:orow1, ocol0:ocol1] = blur[orow0 - irow0 : orow1 - irow0, ocol0 - icol0 : ocol1 - icol0]
        self.coarse_field[orow0 // c : orow1 // c, ocol0 // c : ocol1 // c] = _max_pool(
            self.field[orow0:orow1, ocol0:ocol1], c
        )

    # -- views ---------------------------------------------------------------------------------

    def probability(self) -> FloatArray:
        """p(occupied) per cell (0.5 where never seen)."""
        return _p_occupied(self.logodds)

    def occupancy(self) -> npt.NDArray[np.int8]:
        """map_server-style cells: -1 unknown, else round(100 * p).

        Computed again only over the box the scans integrated since the last call changed (a cell's
        value depends on its own log-odds alone: the same cells as computing them all), in bands of
        rows: the float64 chain over a whole 650 x 650 grid held ~7 MB of temporaries at once (an
        agent's peak memory); a band holds a few hundred kB. Returns a copy the caller may keep."""
        if self._cells is None:
            self._cells = np.empty(self.shape, dtype=np.int8)
            box: Box | None = (0, 0, *self.shape)
        else:
            box = self._cells_stale
        self._cells_stale = None
        if box is not None:
            h, w = self.shape
            r0, c0, r1, c1 = max(box[0], 0), max(box[1], 0), min(box[2], h), min(box[3], w)
            if r1 > r0 and c1 > c0:
                band = max(1, _OCCUPANCY_BAND // (c1 - c0))
                for b0 in range(r0, r1, band):
                    b1 = min(b0 + band, r1)
                    part = np.rint(100.0 * _p_occupied(self.logodds[b0:b1, c0:c1])).astype(np.int8)
                    part[~self.seen[b0:b1, c0:c1]] = -1
                    self._cells[b0:b1, c0:c1] = part
        return self._cells.copy()

    def take_dirty(self) -> Box | None:
        box, self.dirty = self.dirty, None
        return box


def _evidence(logodds: npt.NDArray[np.float32], out: npt.NDArray[np.float32], l_occ: float) -> None:
    """Occupied evidence in [0, 1] into ``out``: 0 for free or unknown, rising with the log-odds above 0."""
    np.divide(logodds, np.float32(l_occ * 2.0), out=out)
    np.maximum(out, np.float32(0.0), out=out)
    np.minimum(out, np.float32(1.0), out=out)


def _blur(pad: npt.NDArray[np.float32], rows: int, cols: int) -> npt.NDArray[np.float32]:
    """The field over the ``rows`` x ``cols`` cells inside ``pad``'s kernel-wide margin (any axes after
    the first two ride along: the tiles of ``_refresh_tiles``): the kernel along rows, then across
    them, each sum in the kernel's order, scaled so a one-cell wall (6/16 blurred across it) reads 1."""
    tmp = np.multiply(pad[:, 0:cols], _KERNEL[0])
    buf = np.empty_like(tmp)
    for i in range(1, 2 * _K + 1):
        tmp += np.multiply(pad[:, i : i + cols], _KERNEL[i], out=buf)
    blur: npt.NDArray[np.float32] = np.multiply(tmp[0:rows], _KERNEL[0])
    buf = buf[0:rows]
    for i in range(1, 2 * _K + 1):
        blur += np.multiply(tmp[i : i + rows], _KERNEL[i], out=buf)
    blur *= np.float32(16.0 / 6.0)
    np.minimum(blur, np.float32(1.0), out=blur)
    return blur


def _max_pool(a: F32, c: int) -> F32:
    """Max over ``c`` x ``c`` blocks (``a``'s sides are multiples of ``c``).

    Element-wise maxima of strided views: numpy's ``reshape(...).max(axis=(1, 3))`` reduces along
    short strided axes, several times slower on the grids the matcher refreshes every scan."""
    cols = a[:, 0::c].copy()
    for i in range(1, c):
        np.maximum(cols, a[:, i::c], out=cols)
    out = cols[0::c].copy()
    for i in range(1, c):
        np.maximum(out, cols[i::c], out=out)
    return out


def _p_occupied(logodds: F32) -> FloatArray:
    """p(occupied) from log-odds, in float64."""
    p: FloatArray = 1.0 - 1.0 / (1.0 + np.exp(logodds.astype(np.float64)))
    return p


_TILE = 8
"""Cells per side of the tiles ``_refresh_cells`` recomputes (rounded up to whole coarse cells)."""
_OCCUPANCY_BAND = 32768
"""Cells per band in ``occupancy``."""
_FREE_CHUNK = 16384
"""Free samples traced at once: bounds ``integrate``'s temporary arrays (a 720-beam turn in a 30 m
hall has ~170k samples: ~10 MB of float64 temporaries at once, now ~1.5 MB) without changing a value."""


def _free_cells(
    sx: float,
    sy: float,
    cos_a: FloatArray,
    sin_a: FloatArray,
    counts: npt.NDArray[np.int64],
    res: float,
    ox: float,
    oy: float,
    w: int,
) -> tuple[npt.NDArray[np.int64], Box | None]:
    """Flat cell indices of every free sample (``counts[i]`` along beam i, at (k + 0.5) cells), and
    their bounding box. Traced in chunks of whole beams, ``_FREE_CHUNK`` samples or so each."""
    ends = np.cumsum(counts)
    parts: list[npt.NDArray[np.int64]] = []
    box: Box | None = None
    b0 = 0
    n = counts.size
    while b0 < n:
        base = int(ends[b0 - 1]) if b0 else 0
        b1 = max(b0 + 1, int(np.searchsorted(ends, base + _FREE_CHUNK, side="right")))
        c = counts[b0:b1]
        total = int(ends[b1 - 1]) - base
        if total:
            beam = np.repeat(np.arange(b0, b1), c)
            starts = ends[b0:b1] - c - base
            k = np.arange(total, dtype=np.float64) - np.repeat(starts, c) + 0.5
            k *= res
            fcol = ((sx + k * cos_a[beam] - ox) / res).astype(np.int64)
            frow = ((sy + k * sin_a[beam] - oy) / res).astype(np.int64)
            parts.append(frow * w + fcol)
        b0 = b1
    # Along a beam a sample's row and column are monotone in k (each step of the arithmetic is), so the
    # samples' box is that of each beam's first and last ones: computed alike, 2 per beam, not all.
    some = counts > 0
    if some.any():
        ends_k = np.concatenate((np.full(int(some.sum()), 0.5), counts[some] - 0.5)) * res
        ca, sa = np.tile(cos_a[some], 2), np.tile(sin_a[some], 2)
        ecol = ((sx + ends_k * ca - ox) / res).astype(np.int64)
        erow = ((sy + ends_k * sa - oy) / res).astype(np.int64)
        box = (int(erow.min()), int(ecol.min()), int(erow.max()) + 1, int(ecol.max()) + 1)
    free = np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
    return free, box


def _unique(a: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """The distinct values of ``a``, sorted (``np.unique`` without its overhead: several times faster on
    the few hundred cells a scan changes)."""
    s = np.sort(a)
    if s.size < 2:
        return s
    keep = np.empty(s.size, dtype=bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    out: npt.NDArray[np.int64] = s[keep]
    return out


def _union(a: Box, b: Box) -> Box:
    return (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
