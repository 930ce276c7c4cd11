"""The wire contract in JSON: a JSON Schema per message, and messages to and from JSON.

Generated from the one place messages are defined (``shared/messages.py`` through
``wire.schema``), so a field added to a message is in its JSON Schema at once. Used where fleet
messages leave msgpack for a format people's tools read: the flight recorder's MCAP channels
(docs/recording.md).

The JSON form of a message is its msgpack form (``wire.encode``: field names as on the wire, enums
as their values, nil as ``null``, every field present) with ``bytes`` as base64 strings
(``contentEncoding: base64``, as Foxglove's schemas write binary). ``to_json`` takes the bytes that
travelled (already validated by ``wire.decode_key``) so a recorder never packs a message again.

Pure Python, no I/O.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import json
import math
import types
import typing
from collections.abc import Callable
from typing import Any

import msgpack
import orjson

from fleetlink.shared import wire

__all__ = [
    "JSON_SCHEMA_DIALECT",
    "from_json",
    "json_schema",
    "schema_bytes",
    "to_json",
    "unpacked_to_json",
    "wire_to_json",
]

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

_Convert = Callable[[Any], Any]


def json_schema(cls: type[wire.Message]) -> dict[str, Any]:
    """The JSON Schema of message class ``cls``: every field required, none other allowed, bounds
    and lengths as the wire checks them (``__post_init__`` cross-field checks are not expressed)."""
    out = _struct_schema(cls)
    out["$schema"] = JSON_SCHEMA_DIALECT
    out["$comment"] = (
        f"fleetlink wire contract {wire.WIRE_VERSION}, topic {cls.TOPIC!r} (generated from shared/messages.py)"
    )
    return out


_SCHEMA_BYTES: dict[type[wire.Message], bytes] = {}
_TO_JSON: dict[type[wire.Message], _Convert | None] = {}
_FROM_JSON: dict[type[wire.Message], _Convert | None] = {}


def schema_bytes(cls: type[wire.Message]) -> bytes:
    """``json_schema(cls)`` as compact UTF-8 JSON (what an MCAP schema record holds); cached."""
    found = _SCHEMA_BYTES.get(cls)
    if found is None:
        found = _SCHEMA_BYTES[cls] = json.dumps(json_schema(cls), separators=(",", ":"), sort_keys=True).encode()
    return found


def _struct_schema(cls: type[Any]) -> dict[str, Any]:
    props: dict[str, Any] = {}
    for spec in wire.schema(cls):
        props[spec.name] = _schema(spec.type, spec.limits)
    return {
        "title": cls.__name__,
        "type": "object",
        "properties": props,
        "required": list(props),
        "additionalProperties": False,
    }


def _bounds(out: dict[str, Any], limits: wire.Limits) -> dict[str, Any]:
    if limits.ge is not None and math.isfinite(limits.ge):
        out["minimum"] = limits.ge
    if limits.le is not None and math.isfinite(limits.le):
        out["maximum"] = limits.le
    return out


def _schema(tp: Any, limits: wire.Limits) -> dict[str, Any]:
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        base, *extras = typing.get_args(tp)
        for extra in extras:
            if isinstance(extra, wire.Limits):
                limits = limits.over(extra)
        return _schema(base, limits)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        inner = args[0] if len(args) == 1 else typing.Union[tuple(args)]  # noqa: UP007
        return {"anyOf": [_schema(inner, limits), {"type": "null"}]}
    if origin in (list, tuple):
        item_tp = typing.get_args(tp)[0]
        return {
            "type": "array",
            "maxItems": limits.max_len,
            "items": _schema(item_tp, limits.item or wire.Limits()),
        }
    if tp is bool:
        return {"type": "boolean"}
    if tp is int:
        return _bounds({"type": "integer"}, limits)
    if tp is float:
        return _bounds({"type": "number"}, limits)
    if tp is str:
        return {"type": "string", "maxLength": limits.max_len or wire.DEFAULT_MAX_STR_LEN}
    if tp is bytes:
        out: dict[str, Any] = {"type": "string", "contentEncoding": "base64"}
        if limits.max_len is not None:
            out["maxLength"] = 4 * ((limits.max_len + 2) // 3)
        return out
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return {"type": "string", "enum": [str(m.value) for m in tp]}
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return _struct_schema(tp)
    raise TypeError(f"no JSON Schema for {tp!r}")


# --------------------------------------------------------------------------------------------------
# Values: only bytes differ between the msgpack form and the JSON form.


def _b64(value: Any) -> Any:
    return base64.b64encode(value).decode("ascii") if isinstance(value, bytes | bytearray) else value


def _unb64(value: Any) -> Any:
    return base64.b64decode(value, validate=True) if isinstance(value, str) else value


def _converter(tp: Any, leaf: _Convert) -> _Convert | None:
    """A function turning the msgpack form of ``tp`` into the JSON form (or back: ``leaf``), or
    None when the two forms are the same (no ``bytes`` inside)."""
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _converter(typing.get_args(tp)[0], leaf)
    if origin in (typing.Union, types.UnionType):
        inner = [c for a in typing.get_args(tp) if a is not type(None) and (c := _converter(a, leaf)) is not None]
        if not inner:
            return None
        one = inner[0]
        return lambda v: None if v is None else one(v)
    if origin in (list, tuple):
        item = _converter(typing.get_args(tp)[0], leaf)
        if item is None:
            return None
        return lambda v: [item(x) for x in v]
    if tp is bytes:
        return leaf
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        fields = [(s.name, c) for s in wire.schema(tp) if (c := _converter(s.type, leaf)) is not None]
        if not fields:
            return None

        def struct(v: Any) -> Any:
            out = dict(v)
            for name, conv in fields:
                out[name] = conv(out[name])
            return out

        return struct
    return None


def _to_json_of(cls: type[wire.Message]) -> _Convert | None:
    if cls not in _TO_JSON:
        _TO_JSON[cls] = _converter(cls, _b64)
    return _TO_JSON[cls]


def _from_json_of(cls: type[wire.Message]) -> _Convert | None:
    if cls not in _FROM_JSON:
        _FROM_JSON[cls] = _converter(cls, _unb64)
    return _FROM_JSON[cls]


def wire_to_json(cls: type[wire.Message], payload: bytes) -> bytes:
    """The JSON form (UTF-8) of the msgpack ``payload`` of a ``cls`` message that ``wire`` has
    already accepted (``decode_key``): unpacked once, bytes as base64, no re-validation.

    Written by orjson (compact, as ``json.dumps(obj, separators=(",", ":"))`` writes it but for the
    spelling of some floats, ``1e-07`` as ``1e-7``: the same numbers): ~1 us for a pose where
    ``json.dumps`` took ~8 us, and a flight recorder converts a thousand a second. A wire-valid
    message has only finite floats and integers of at most 64 bits, which orjson writes."""
    return unpacked_to_json(cls, msgpack.unpackb(payload, raw=False))


def unpacked_to_json(cls: type[wire.Message], obj: Any) -> bytes:
    """``wire_to_json`` of the value ``wire.decode_key_unpacked`` unpacked and validated (not
    changed: bytes are converted in a copy)."""
    conv = _to_json_of(cls)
    if conv is not None:
        obj = conv(obj)
    return orjson.dumps(obj)


def to_json(msg: wire.Message) -> bytes:
    """The JSON form (UTF-8) of ``msg`` (encoded and validated by ``wire.encode`` first)."""
    return wire_to_json(type(msg), wire.encode(msg))


def from_json(cls: type[wire.Message], data: bytes | str) -> wire.Message:
    """The ``cls`` message in ``data`` (its JSON form), validated as the wire validates a received
    message. Raises only ``wire.WireError`` (bad JSON, bad base64, anything the schema refuses)."""
    try:
        obj = json.loads(data)
        conv = _from_json_of(cls)
        if conv is not None and isinstance(obj, dict):
            obj = conv(obj)
        packed = msgpack.packb(obj, use_bin_type=True)
    except (ValueError, TypeError, KeyError, OverflowError) as exc:
        raise wire.WireError(
            f"not a {cls.__name__} in JSON ({type(exc).__name__}: {str(exc)[:80]})", "payload"
        ) from None
    return wire.decode(cls, packed)
