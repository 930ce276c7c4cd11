"""UWB anchors: fixed radios at known positions in the plan's frame (x east, y north, z up, metres).

Pure: no I/O. Anchors come from configuration, from a floor plan (``plan.anchors``) or from a
scenario (which may override its plan's).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["Anchor", "anchor_array", "anchors_from", "check_anchors"]


@dataclass(frozen=True, slots=True)
class Anchor:
    """One UWB anchor. ``id`` is what ranges and fixes name it by."""

    id: str
    x: float
    y: float
    z: float

    def __post_init__(self) -> None:
        for name in ("x", "y", "z"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"anchor {self.id!r}: {name} must be a finite number, got {v!r}")


def anchors_from(items: Iterable[Any]) -> tuple[Anchor, ...]:
    """Anchors from anything shaped ``(id, x, y, z)``: plan anchors, scenario tuples, ``Anchor``s."""
    out = []
    for a in items:
        if isinstance(a, Anchor):
            out.append(a)
        else:
            aid, x, y, z = a
            out.append(Anchor(str(aid), float(x), float(y), float(z)))
    return check_anchors(out)


def check_anchors(anchors: Sequence[Anchor]) -> tuple[Anchor, ...]:
    """The anchors as a tuple; ValueError if an id repeats."""
    seen: set[str] = set()
    for a in anchors:
        if a.id in seen:
            raise ValueError(f"anchor {a.id!r} appears twice")
        seen.add(a.id)
    return tuple(anchors)


def anchor_array(anchors: Sequence[Anchor]) -> npt.NDArray[np.float64]:
    """Shape (N, 3): x, y, z of each anchor, in order."""
    return np.array([(a.x, a.y, a.z) for a in anchors], dtype=np.float64).reshape(-1, 3)
