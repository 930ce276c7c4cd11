"""Planar poses ``(x, y, theta)``: the composition and inverse the mapping modules, the fusion and
the console (a robot drawn through its frame on the fleet map) use.

    compose(a, b)    a (+) b: pose b given in a's frame, expressed in a's parent frame
    relative(a, b)   a^-1 (+) b: pose b seen from a
    inverse(p)       p^-1
    wrap(a)          an angle into [-pi, pi)
    apart(p, q, xy, theta)  p and q more than xy metres or theta radians apart

Pure; no I/O.
"""

from __future__ import annotations

import math

__all__ = ["Pose", "apart", "compose", "inverse", "relative", "wrap"]

Pose = tuple[float, float, float]


def wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def compose(a: Pose, b: Pose) -> Pose:
    """a (+) b: pose b given in a's frame, expressed in a's parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2]))


def relative(a: Pose, b: Pose) -> Pose:
    """a^-1 (+) b: pose b seen from a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2]))


def inverse(p: Pose) -> Pose:
    """p^-1: the parent frame seen from p."""
    c, s = math.cos(p[2]), math.sin(p[2])
    return (-(c * p[0] + s * p[1]), -(-s * p[0] + c * p[1]), wrap(-p[2]))


def apart(p: Pose, q: Pose, xy: float, theta: float) -> bool:
    """``p`` and ``q`` more than ``xy`` metres apart, or their headings more than ``theta`` radians."""
    return math.hypot(p[0] - q[0], p[1] - q[1]) > xy or abs(math.remainder(p[2] - q[2], math.tau)) > theta
