"""Foxglove's well-known message schemas (JSON encoding), so Foxglove and Lichtblick draw fleetlink
poses, maps and scans without a plug-in.

Schemas as Foxglove publishes them (github.com/foxglove/schemas, ``schemas/jsonschema``):
``foxglove.PoseInFrame``, ``foxglove.Grid`` (an occupancy map is a grid of one ``INT8`` field),
``foxglove.LaserScan`` and ``foxglove.FrameTransforms``. Builders return plain dicts ready for
``json.dumps``. Times are seconds since the Unix epoch (``{sec, nsec}``); frames are fleetlink's:
``map`` is the fleet map's frame (the site (UWB) frame, when any robot maps in it), ``<robot>/map``
the own map frame of a robot without UWB.

Pure Python, no I/O.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Sequence
from typing import Any, Final

import orjson

__all__ = [
    "FLOAT32",
    "FRAME_TRANSFORMS",
    "GRID",
    "INT8",
    "LASER_SCAN",
    "MAP_FRAME",
    "POSE_IN_FRAME",
    "SCHEMAS",
    "dumps",
    "frame_transforms",
    "grid",
    "laser_scan",
    "pose_in_frame",
    "pose_in_frame_json",
    "schema_bytes",
    "timestamp",
]

POSE_IN_FRAME: Final = "foxglove.PoseInFrame"
GRID: Final = "foxglove.Grid"
LASER_SCAN: Final = "foxglove.LaserScan"
FRAME_TRANSFORMS: Final = "foxglove.FrameTransforms"
MAP_FRAME: Final = "map"
"""The fleet map's frame: the site frame (the UWB frame every pose, goal and map origin is in) when
any robot maps in it."""
INT8: Final = 2
"""``foxglove.NumericType.INT8``."""
FLOAT32: Final = 7
"""``foxglove.NumericType.FLOAT32`` (little-endian, as Foxglove reads every multi-byte field)."""
_CELL_BYTES: Final = {INT8: 1, FLOAT32: 4}


def _num(description: str) -> dict[str, Any]:
    return {"type": "number", "description": description}


def _time(description: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": "time",
        "description": description,
        "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
        },
    }


def _pose(description: str) -> dict[str, Any]:
    return {
        "title": "foxglove.Pose",
        "description": description,
        "type": "object",
        "properties": {
            "position": {
                "title": "foxglove.Vector3",
                "type": "object",
                "properties": {axis: _num(f"{axis} coordinate length") for axis in "xyz"},
            },
            "orientation": {
                "title": "foxglove.Quaternion",
                "type": "object",
                "properties": {axis: _num(f"{axis} value") for axis in "xyzw"},
            },
        },
    }


def _message(title: str, description: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object", "properties": props}


_NUMERIC_TYPES = ("UNKNOWN", "UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "FLOAT32", "FLOAT64")

SCHEMAS: Final[dict[str, dict[str, Any]]] = {
    POSE_IN_FRAME: _message(
        POSE_IN_FRAME,
        "A timestamped pose for an object or reference frame in 3D space",
        {
            "timestamp": _time("Timestamp of pose"),
            "frame_id": {"type": "string", "description": "Frame of reference for pose position and orientation"},
            "pose": _pose("Pose in 3D space"),
        },
    ),
    GRID: _message(
        GRID,
        "A 2D grid of data",
        {
            "timestamp": _time("Timestamp of grid"),
            "frame_id": {"type": "string", "description": "Frame of reference"},
            "pose": _pose("Origin of grid's corner relative to frame of reference"),
            "column_count": {"type": "integer", "minimum": 0, "description": "Number of grid columns"},
            "cell_size": {
                "title": "foxglove.Vector2",
                "type": "object",
                "properties": {"x": _num("x coordinate length"), "y": _num("y coordinate length")},
            },
            "row_stride": {"type": "integer", "minimum": 0, "description": "Number of bytes between rows in `data`"},
            "cell_stride": {"type": "integer", "minimum": 0, "description": "Number of bytes between cells in a row"},
            "fields": {
                "type": "array",
                "description": "Fields in `data`",
                "items": {
                    "title": "foxglove.PackedElementField",
                    "type": "object",
                    "properties": {
                        "name": {"type": "string"},
                        "offset": {"type": "integer", "minimum": 0},
                        "type": {
                            "title": "foxglove.NumericType",
                            "oneOf": [{"title": name, "const": i} for i, name in enumerate(_NUMERIC_TYPES)],
                        },
                    },
                },
            },
            "data": {"type": "string", "contentEncoding": "base64", "description": "Grid cell data, row-major"},
        },
    ),
    FRAME_TRANSFORMS: _message(
        FRAME_TRANSFORMS,
        "An array of FrameTransform messages",
        {
            "transforms": {
                "type": "array",
                "description": "Array of transforms",
                "items": {
                    "title": "foxglove.FrameTransform",
                    "type": "object",
                    "description": "A transform between two reference frames in 3D space",
                    "properties": {
                        "timestamp": _time("Timestamp of transform"),
                        "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
                        "child_frame_id": {"type": "string", "description": "Name of the child frame"},
                        "translation": {
                            "title": "foxglove.Vector3",
                            "type": "object",
                            "description": "Translation component of the transform",
                            "properties": {axis: _num(f"{axis} coordinate length") for axis in "xyz"},
                        },
                        "rotation": {
                            "title": "foxglove.Quaternion",
                            "type": "object",
                            "description": "Rotation component of the transform",
                            "properties": {axis: _num(f"{axis} value") for axis in "xyzw"},
                        },
                    },
                },
            }
        },
    ),
    LASER_SCAN: _message(
        LASER_SCAN,
        "A single scan from a planar laser range-finder",
        {
            "timestamp": _time("Timestamp of scan"),
            "frame_id": {"type": "string", "description": "Frame of reference"},
            "pose": _pose("Origin of scan relative to frame of reference"),
            "start_angle": _num("Bearing of first point, in radians"),
            "end_angle": _num("Bearing of last point, in radians"),
            "ranges": {"type": "array", "items": {"type": "number"}, "description": "Distance of detections"},
            "intensities": {"type": "array", "items": {"type": "number"}, "description": "Intensity of detections"},
        },
    ),
}


_SCHEMA_BYTES: dict[str, bytes] = {}


def schema_bytes(name: str) -> bytes:
    """The JSON Schema of Foxglove message ``name`` as UTF-8 JSON (an MCAP schema record's data)."""
    found = _SCHEMA_BYTES.get(name)
    if found is None:
        found = _SCHEMA_BYTES[name] = json.dumps(SCHEMAS[name], separators=(",", ":"), sort_keys=True).encode()
    return found


def timestamp(t: float) -> dict[str, int]:
    """Epoch seconds as Foxglove's ``{sec, nsec}`` (never negative)."""
    t = max(0.0, t)
    sec = math.floor(t)
    nsec = round((t - sec) * 1e9)  # from the fraction: t * 1e9 would lose the nanoseconds
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return {"sec": int(sec), "nsec": int(nsec)}


def _planar(x: float, y: float, theta: float) -> dict[str, Any]:
    half = theta / 2.0
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)},
    }


def pose_in_frame(t: float, x: float, y: float, theta: float, frame: str = MAP_FRAME) -> dict[str, Any]:
    """``foxglove.PoseInFrame``: a planar pose (heading ``theta`` rad about +z) in ``frame``."""
    return {"timestamp": timestamp(t), "frame_id": frame, "pose": _planar(x, y, theta)}


def pose_in_frame_json(t: float, x: float, y: float, theta: float, frame: str = MAP_FRAME) -> bytes:
    """``pose_in_frame(...)`` as compact JSON, written by orjson from the fewest dicts (a recorder
    writes one per pose: ~1.2 us, where building ``pose_in_frame`` and ``json.dumps`` took ~7)."""
    half = theta / 2.0
    return dumps(
        {
            "timestamp": timestamp(t),
            "frame_id": frame,
            "pose": {
                "position": {"x": float(x), "y": float(y), "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)},
            },
        }
    )


def dumps(obj: object) -> bytes:
    """Compact JSON: orjson (several times ``json.dumps``'s speed), or ``json`` for what orjson
    refuses (an integer beyond 64 bits: the seconds of a wire-valid but absurd timestamp)."""
    try:
        return orjson.dumps(obj)
    except TypeError:
        return json.dumps(obj, separators=(",", ":")).encode()


def grid(
    t: float,
    *,
    origin: tuple[float, float],
    resolution: float,
    width: int,
    cells: bytes,
    name: str = "occupancy",
    frame: str = MAP_FRAME,
    numeric_type: int = INT8,
) -> dict[str, Any]:
    """``foxglove.Grid`` of one field ``name``: ``cells`` row-major, row 0 at ``origin``'s y (the
    wire's map layout), ``width`` cells a row. ``INT8`` (the default): an occupancy map, -1 unknown
    and 0-100 occupancy percent; ``FLOAT32``: little-endian floats (a dose layer's J/m²)."""
    size = _CELL_BYTES[numeric_type]
    return {
        "timestamp": timestamp(t),
        "frame_id": frame,
        "pose": _planar(origin[0], origin[1], 0.0),
        "column_count": width,
        "cell_size": {"x": resolution, "y": resolution},
        "row_stride": width * size,
        "cell_stride": size,
        "fields": [{"name": name, "offset": 0, "type": numeric_type}],
        "data": base64.b64encode(cells).decode("ascii"),
    }


def laser_scan(
    t: float,
    *,
    pose: tuple[float, float, float],
    start_angle: float,
    end_angle: float,
    ranges: Sequence[float],
    intensities: Sequence[float] = (),
    frame: str = MAP_FRAME,
) -> dict[str, Any]:
    """``foxglove.LaserScan`` taken at ``pose`` (x, y, heading) in ``frame``; ranges in metres at equal
    steps from ``start_angle`` to ``end_angle`` (radians, counter-clockwise from the heading)."""
    return {
        "timestamp": timestamp(t),
        "frame_id": frame,
        "pose": _planar(*pose),
        "start_angle": start_angle,
        "end_angle": end_angle,
        "ranges": list(ranges),
        "intensities": list(intensities),
    }


def frame_transforms(t: float, transforms: Sequence[tuple[str, str, float, float, float]]) -> dict[str, Any]:
    """``foxglove.FrameTransforms``: each ``(parent, child, x, y, theta)`` puts frame ``child`` at the
    planar pose (x, y, heading theta) in ``parent``."""
    out = []
    for parent, child, x, y, theta in transforms:
        half = theta / 2.0
        out.append(
            {
                "timestamp": timestamp(t),
                "parent_frame_id": parent,
                "child_frame_id": child,
                "translation": {"x": x, "y": y, "z": 0.0},
                "rotation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)},
            }
        )
    return {"transforms": out}
