"""The UV dose layer as it travels: float32 cells (J/m²) compressed with zlib, whole or as a patch.

Pure functions plus ``SharedDose``, the receiving side's copy that applies ``DoseUpdate`` patches
and says when it needs a fresh ``DoseSnapshot`` (as ``map_codec.SharedMap`` does for maps). The
message classes are in ``shared/messages.py``; the dose model and ``DoseGrid`` in ``shared/dose.py``.

A layer never claims more dose than the agent counted: every value is rounded *down* to float32
(``to_float32_down``), and a snapshot too large for one message keeps fewer mantissa bits, cut
down too (``mantissa_bits``), rather than coarser cells (the layers of several robots must stay
on one lattice to add up cell by cell). Decoding checks everything a sender could get wrong (the
inflated size, NaN, infinities, negative or absurd doses, an origin off the lattice, a patch
outside the layer) and raises ``WireError`` naming it.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetlink.shared.dose import DoseGrid, Lamp
from fleetlink.shared.map_codec import paste, patch_follows, patch_outside, patch_place, patch_window
from fleetlink.shared.messages import (
    MAX_DOSE_CELLS,
    MAX_DOSE_DATA,
    MAX_DOSE_J_M2,
    DoseEncoding,
    DoseLamp,
    DoseSnapshot,
    DoseUpdate,
)
from fleetlink.shared.wire import WireError

__all__ = [
    "ENCODING",
    "FULL_BITS",
    "SharedDose",
    "check_lattice",
    "decode_cells",
    "encode_cells",
    "patch_fields",
    "snapshot_fields",
    "to_float32_down",
]

ENCODING = DoseEncoding.ZLIB_F32LE
FULL_BITS = 23
"""A float32's mantissa bits: the cells as float32, nothing cut."""
SNAPSHOT_BITS = (FULL_BITS, 16, 12, 9, 6, 3, 0)
"""What a snapshot too large for one message tries next, in order."""
PATCH_LEVEL = 1
"""zlib level of ``DoseUpdate`` patches: sent every second and never kept, so speed wins."""
Cells = npt.NDArray[np.float32]


def to_float32_down(dose: npt.ArrayLike, mantissa_bits: int = FULL_BITS) -> Cells:
    """``dose`` (J/m², finite, >= 0) as float32, each value rounded down (never up), to at most
    ``MAX_DOSE_J_M2``, keeping ``mantissa_bits`` (0-23) of the mantissa (the rest cut to zero, which
    for a positive number is rounding down)."""
    if not 0 <= mantissa_bits <= FULL_BITS:
        raise ValueError(f"mantissa_bits must be 0-{FULL_BITS}, got {mantissa_bits}")
    a = np.minimum(np.asarray(dose, dtype=np.float64), MAX_DOSE_J_M2)
    f: Cells = a.astype(np.float32)
    over = f.astype(np.float64) > a
    if over.any():
        f[over] = np.nextafter(f[over], np.float32(0.0))
    if mantissa_bits < FULL_BITS:
        bits = f.view(np.uint32)
        bits &= np.uint32((0xFFFFFFFF << (FULL_BITS - mantissa_bits)) & 0xFFFFFFFF)
    return f


def encode_cells(dose: npt.ArrayLike, level: int = 6, mantissa_bits: int = FULL_BITS) -> bytes:
    """The cells rounded down to float32 (``to_float32_down``), little-endian, zlib-compressed."""
    f = np.ascontiguousarray(to_float32_down(dose, mantissa_bits), dtype="<f4")
    return zlib.compress(f.tobytes(), level)


def decode_cells(data: bytes, width: int, height: int) -> Cells:
    """Inflate exactly ``width * height`` float32 cells; ``WireError`` for anything else (never more memory)."""
    n = width * height
    if n > MAX_DOSE_CELLS:
        raise WireError(f"{width} x {height} cells is over the limit of {MAX_DOSE_CELLS}", "cells")
    d = zlib.decompressobj()
    try:
        raw = d.decompress(data, 4 * n + 1)
    except zlib.error as exc:
        raise WireError(f"not valid zlib data ({exc})", "cells") from None
    what = f"expected {4 * n} bytes ({width} x {height} float32)"
    if len(raw) > 4 * n or d.unconsumed_tail:
        raise WireError(f"{what}, got more", "cells")
    if len(raw) < 4 * n:
        raise WireError(f"{what}, got {len(raw)}", "cells")
    if not d.eof:
        raise WireError(f"{what}: the zlib stream does not end there", "cells")
    a: Cells = np.frombuffer(raw, dtype="<f4").astype(np.float32).reshape(height, width)
    if a.size:
        if not np.isfinite(a).all():
            raise WireError("not finite (NaN or infinity) in some cell", "cells")
        lo, hi = float(a.min()), float(a.max())
        if lo < 0.0 or hi > MAX_DOSE_J_M2:
            raise WireError(f"doses must be 0-{MAX_DOSE_J_M2:g} J/m², got {lo:g}..{hi:g}", "cells")
    return a


def check_lattice(resolution: float, origin: tuple[float, float]) -> None:
    """WireError unless cell centres lie on multiples of ``resolution`` (every layer's lattice)."""
    for name, o in zip(("origin_x", "origin_y"), origin, strict=True):
        k = o / resolution + 0.5
        if not (math.isfinite(k) and abs(k - round(k)) < 1e-6):
            raise WireError(f"{o!r} is not on the {resolution:g} m lattice (cell centres on multiples of it)", name)


def _fits(n_cells: int) -> bool:
    """Even incompressible cells would fit (zlib's ``compressBound``)."""
    n = 4 * n_cells
    return n + (n >> 12) + (n >> 14) + (n >> 25) + 13 <= MAX_DOSE_DATA


def _whole(dose: npt.NDArray[np.float64]) -> tuple[bytes, int] | None:
    """The cells compressed and the mantissa bits kept: all of them if they fit in one message,
    else the most that do (tried at level 1, the bytes at level 6 unless, oddly, larger)."""
    if _fits(dose.size):
        return encode_cells(dose), FULL_BITS
    for bits in SNAPSHOT_BITS:
        quick = encode_cells(dose, 1, bits)
        if len(quick) <= MAX_DOSE_DATA:
            best = encode_cells(dose, 6, bits)
            return (best if len(best) <= len(quick) else quick), bits
    return None


def _common(
    resolution: float, origin: tuple[float, float], target_j_m2: float, lamp_on_s: float, unplaced_s: float
) -> dict[str, Any]:
    return {
        "resolution": float(resolution),
        "origin_x": float(origin[0]),
        "origin_y": float(origin[1]),
        "target_j_m2": float(target_j_m2),
        "lamp_on_s": float(lamp_on_s),
        "unplaced_s": float(unplaced_s),
        "encoding": ENCODING,
    }


def snapshot_fields(
    dose: npt.NDArray[np.float64],
    resolution: float,
    origin: tuple[float, float],
    version: int,
    *,
    target_j_m2: float,
    lamp_on_s: float,
    unplaced_s: float,
    lamp: Lamp,
) -> dict[str, Any] | None:
    """Keyword fields of a ``DoseSnapshot`` (fewer mantissa bits until it fits), or None when even
    0 bits do not fit (a layer of millions of distinct doses: the caller says so)."""
    whole = _whole(dose)
    if whole is None:
        return None
    data, bits = whole
    return {
        "version": int(version),
        **_common(resolution, origin, target_j_m2, lamp_on_s, unplaced_s),
        "width": int(dose.shape[1]),
        "height": int(dose.shape[0]),
        "mantissa_bits": bits,
        "cells": data,
        "lamp": DoseLamp(
            uvc_power_w=lamp.uvc_power_w,
            height_m=lamp.height_m,
            tube_length_m=lamp.tube_length_m,
            min_distance_m=lamp.min_distance_m,
        ),
    }


def patch_fields(
    dose: npt.NDArray[np.float64],
    resolution: float,
    origin: tuple[float, float],
    box: tuple[int, int, int, int],
    version: int,
    base_version: int,
    *,
    target_j_m2: float,
    lamp_on_s: float,
    unplaced_s: float,
) -> dict[str, Any] | None:
    """Keyword fields of a ``DoseUpdate`` for ``box`` (row0, col0, row1, col1), or None if it does not fit."""
    window = patch_window(dose.shape, box)
    r0, c0, r1, c1 = window
    data = encode_cells(dose[r0:r1, c0:c1], PATCH_LEVEL)
    if len(data) > MAX_DOSE_DATA:
        return None
    return {
        "version": int(version),
        "base_version": int(base_version),
        **_common(resolution, origin, target_j_m2, lamp_on_s, unplaced_s),
        **patch_place(dose.shape, window),
        "cells": data,
    }


@dataclass(slots=True)
class SharedDose:
    """A copy of one robot's dose layer, kept current from snapshots and updates."""

    cells: Cells
    resolution: float
    origin: tuple[float, float]
    version: int
    target_j_m2: float
    lamp_on_s: float
    unplaced_s: float
    mantissa_bits: int = FULL_BITS
    """The fewest mantissa bits any of its cells kept (the snapshot's; patches keep all 23)."""
    lamp: Lamp | None = None
    """The robot's lamp (from the snapshot)."""

    @classmethod
    def from_snapshot(cls, msg: DoseSnapshot) -> SharedDose:
        """The layer in ``msg``; ``WireError`` for cells that cannot be right."""
        check_lattice(msg.resolution, (msg.origin_x, msg.origin_y))
        lp = msg.lamp
        try:
            lamp = Lamp(lp.uvc_power_w, lp.height_m, lp.tube_length_m, lp.min_distance_m)
        except ValueError as exc:
            raise WireError(f"not a lamp: {exc}", "lamp") from None
        return cls(
            decode_cells(msg.cells, msg.width, msg.height),
            msg.resolution,
            (msg.origin_x, msg.origin_y),
            msg.version,
            msg.target_j_m2,
            msg.lamp_on_s,
            msg.unplaced_s,
            msg.mantissa_bits,
            lamp,
        )

    def apply(self, msg: DoseUpdate) -> bool:
        """Apply a patch; False (unchanged) when it does not follow this copy: fetch a snapshot then.

        ``WireError`` for a patch that cannot be right (outside the layer, cells of the wrong size
        or values)."""
        if patch_outside(msg):
            raise WireError(
                f"the patch ({msg.col}, {msg.row}) + {msg.patch_width} x {msg.patch_height} lies outside the "
                f"{msg.width} x {msg.height} layer",
                "col",
            )
        if not patch_follows(msg, self.version, self.cells, self.resolution, self.origin):
            return False
        paste(self.cells, msg, decode_cells(msg.cells, msg.patch_width, msg.patch_height))
        self.version = msg.version
        self.target_j_m2, self.lamp_on_s, self.unplaced_s = msg.target_j_m2, msg.lamp_on_s, msg.unplaced_s
        return True

    def grid(self) -> DoseGrid:
        """The layer as a ``DoseGrid`` (float64, its lamp-on seconds), to merge and report on."""
        g = DoseGrid.from_array(self.cells.astype(np.float64), self.resolution, self.origin)
        g.lamp_seconds = self.lamp_on_s
        return g
