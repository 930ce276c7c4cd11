"""The map as it travels: int8 cells (-1 unknown, 0-100) compressed with zlib, whole or as a patch.

Pure functions plus ``SharedMap``, the receiving side's copy that applies ``MapUpdate`` patches and
says when it needs a fresh ``MapSnapshot``. The message classes are in ``shared/messages.py``.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from fleetlink.shared.messages import MAX_MAP_CELLS, MAX_MAP_DATA, MapEncoding, MapSnapshot, MapUpdate

__all__ = [
    "ENCODING",
    "SharedMap",
    "decode_cells",
    "encode_cells",
    "fits_whole",
    "patch_fields",
    "snapshot_fields",
]

ENCODING = MapEncoding.ZLIB_INT8
Cells = npt.NDArray[np.int8]


def encode_cells(cells: npt.ArrayLike, level: int = 6) -> bytes:
    a = np.ascontiguousarray(np.asarray(cells, dtype=np.int8))
    return zlib.compress(a.tobytes(), level)


def decode_cells(data: bytes, width: int, height: int) -> Cells:
    """Decompress exactly ``width * height`` cells; ValueError for anything else (never more memory)."""
    n = width * height
    if n > MAX_MAP_CELLS:
        raise ValueError(f"{width} x {height} cells is over the limit")
    d = zlib.decompressobj()
    try:
        raw = d.decompress(data, n + 1)
    except zlib.error as exc:
        raise ValueError(f"cells: not valid zlib data ({exc})") from None
    if len(raw) != n or d.unconsumed_tail or not d.eof:
        raise ValueError(f"cells: expected {n} bytes, got {len(raw)}{'+' if d.unconsumed_tail else ''}")
    a = np.frombuffer(raw, dtype=np.int8).reshape(height, width).copy()
    if a.size and (a.min() < -1 or a.max() > 100):
        raise ValueError("cells: values must be -1 or 0-100")
    return a


def _downsample(cells: Cells) -> Cells:
    """Half the resolution: occupied wins, then free, then unknown (safe for planning)."""
    h, w = cells.shape
    p = np.full((h + h % 2, w + w % 2), -1, dtype=np.int8)
    p[:h, :w] = cells
    blocks = (
        p.reshape(p.shape[0] // 2, 2, p.shape[1] // 2, 2)
        .transpose(0, 2, 1, 3)
        .reshape(p.shape[0] // 2, p.shape[1] // 2, 4)
    )
    out: Cells = blocks.max(axis=2)
    return out


PATCH_LEVEL = 1
"""zlib level of ``MapUpdate`` patches: sent every second or so and never kept, so speed wins
(level 1 compresses an office map ~3x faster than 6, ~30% larger)."""


def _surely_fits(cells: Cells) -> bool:
    """Even incompressible cells would fit (zlib's ``compressBound``)."""
    n = int(cells.size)
    return n + (n >> 12) + (n >> 14) + (n >> 25) + 13 <= MAX_MAP_DATA


def _whole(cells: Cells) -> bytes | None:
    """The cells compressed, if they fit in one snapshot at this resolution, else None.

    Whether they fit is decided at level 1 (fast); the bytes are level 6 unless, oddly, larger."""
    if not _surely_fits(cells):
        quick = encode_cells(cells, 1)
        if len(quick) > MAX_MAP_DATA:
            return None
        best = encode_cells(cells)
        return best if len(best) <= len(quick) else quick
    return encode_cells(cells)


def fits_whole(cells: Cells) -> bool:
    """Whether ``snapshot_fields`` keeps these cells at full resolution (so patches of them apply)."""
    return _surely_fits(cells) or len(encode_cells(cells, 1)) <= MAX_MAP_DATA


class Patch(Protocol):
    """What a grid update (``MapUpdate``, ``DoseUpdate``) says of where its patch goes."""

    @property
    def version(self) -> int: ...
    @property
    def base_version(self) -> int: ...
    @property
    def resolution(self) -> float: ...
    @property
    def origin_x(self) -> float: ...
    @property
    def origin_y(self) -> float: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def col(self) -> int: ...
    @property
    def row(self) -> int: ...
    @property
    def patch_width(self) -> int: ...
    @property
    def patch_height(self) -> int: ...


def patch_window(shape: tuple[int, ...], box: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """``box`` (row0, col0, row1, col1) clipped to a grid of ``shape`` (never of negative size)."""
    h, w = shape[0], shape[1]
    r0, c0, r1, c1 = max(0, box[0]), max(0, box[1]), min(h, box[2]), min(w, box[3])
    return r0, c0, max(r0, r1), max(c0, c1)


def patch_place(shape: tuple[int, ...], window: tuple[int, int, int, int]) -> dict[str, int]:
    """An update's fields that place a patch ``window`` in a grid of ``shape``."""
    r0, c0, r1, c1 = window
    return {
        "width": int(shape[1]),
        "height": int(shape[0]),
        "col": int(c0),
        "row": int(r0),
        "patch_width": int(c1 - c0),
        "patch_height": int(r1 - r0),
    }


def patch_outside(msg: Patch) -> bool:
    """The patch reaches beyond the grid it says it belongs to (the update cannot be right)."""
    return msg.col + msg.patch_width > msg.width or msg.row + msg.patch_height > msg.height


def patch_follows(
    msg: Patch, version: int, cells: npt.NDArray[Any], resolution: float, origin: tuple[float, float]
) -> bool:
    """The update follows a copy at ``version`` of this grid (else: fetch a snapshot)."""
    if msg.base_version != version or msg.version <= version:
        return False
    if (msg.width, msg.height) != (cells.shape[1], cells.shape[0]):
        return False
    return msg.resolution == resolution and (msg.origin_x, msg.origin_y) == origin


def paste(cells: npt.NDArray[Any], msg: Patch, patch: npt.NDArray[Any]) -> None:
    cells[msg.row : msg.row + msg.patch_height, msg.col : msg.col + msg.patch_width] = patch


def snapshot_fields(
    cells: Cells, resolution: float, origin: tuple[float, float], version: int, began: float = 0.0
) -> dict[str, Any]:
    """Keyword fields of a ``MapSnapshot`` (of the map begun at ``began``); halves the resolution until
    the compressed cells fit."""
    data = _whole(cells)
    while data is None:
        cells = _downsample(cells)
        resolution *= 2.0
        data = _whole(cells)
    return {
        "version": version,
        "resolution": float(resolution),
        "origin_x": float(origin[0]),
        "origin_y": float(origin[1]),
        "width": int(cells.shape[1]),
        "height": int(cells.shape[0]),
        "encoding": ENCODING,
        "cells": data,
        "began": float(began),
    }


def patch_fields(
    cells: Cells,
    resolution: float,
    origin: tuple[float, float],
    box: tuple[int, int, int, int],
    version: int,
    base_version: int,
    began: float = 0.0,
) -> dict[str, Any] | None:
    """Keyword fields of a ``MapUpdate`` for ``box`` (row0, col0, row1, col1) of the map begun at
    ``began``, or None if it does not fit."""
    window = patch_window(cells.shape, box)
    r0, c0, r1, c1 = window
    data = encode_cells(cells[r0:r1, c0:c1], PATCH_LEVEL)
    if len(data) > MAX_MAP_DATA:
        return None
    return {
        "version": version,
        "base_version": base_version,
        "resolution": float(resolution),
        "origin_x": float(origin[0]),
        "origin_y": float(origin[1]),
        **patch_place(cells.shape, window),
        "encoding": ENCODING,
        "cells": data,
        "began": float(began),
    }


@dataclass(slots=True)
class SharedMap:
    """A copy of another robot's map, kept current from snapshots and updates."""

    cells: Cells
    resolution: float
    origin: tuple[float, float]
    version: int
    began: float = 0.0
    """Which of its robot's maps this is a copy of (``MapSnapshot.began``)."""

    @classmethod
    def from_snapshot(cls, msg: MapSnapshot) -> SharedMap:
        return cls(
            decode_cells(msg.cells, msg.width, msg.height),
            msg.resolution,
            (msg.origin_x, msg.origin_y),
            msg.version,
            msg.began,
        )

    def apply(self, msg: MapUpdate) -> bool:
        """Apply a patch; False (unchanged) when it does not follow this copy (another map's, or not
        from this version): fetch a snapshot then.

        ValueError for a patch that cannot be right (outside the map, cells of the wrong size)."""
        if patch_outside(msg):
            raise ValueError("the patch lies outside the map")
        if msg.began != self.began or not patch_follows(msg, self.version, self.cells, self.resolution, self.origin):
            return False
        paste(self.cells, msg, decode_cells(msg.cells, msg.patch_width, msg.patch_height))
        self.version = msg.version
        return True
