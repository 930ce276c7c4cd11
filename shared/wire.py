"""The wire contract: message header, declarative schema and a validating msgpack codec.

A message is a frozen, slotted dataclass deriving from ``Message`` with a ``TOPIC`` class
attribute. Its fields are typed with a small set of types, and constrained with ``Limits``
(``bounded``/``sized``) given either as ``Annotated`` metadata or as
``dataclasses.field(metadata={WIRE: ...})``::

    @register
    @dataclass(frozen=True, slots=True, kw_only=True)
    class Pose(Message):
        TOPIC: ClassVar[str] = "pose"
        x: float
        score: Annotated[float, bounded(0.0, 1.0)]
        note: Annotated[str, sized(64)]
        ranges: Annotated[tuple[float, ...], sized(360, item=bounded(0.0))]

Supported field types: ``float`` (accepts int on decode, rejects bool, NaN and inf), ``int``
(rejects bool), ``bool``, ``str``, ``bytes``, enums with ``str`` values, ``X | None``, nested
dataclasses, and ``list[X]`` / ``tuple[X, ...]`` (which must have a ``max_len``).

``encode(msg)`` produces a msgpack map ``{"header": {...}, "<field>": value, ...}``;
``decode(cls, data)`` / ``decode_any(topic, data)`` / ``decode_key(key, data)`` validate everything
and raise nothing but ``WireError`` (a ``ValueError``) whose ``reason`` names the offending
field, e.g. ``"battery_percent: 150.0 out of range [0.0, 100.0]"``. Validators are compiled once
per class; no type introspection happens per message. Each class also gets a generated decoder
(``_generate``: straight-line checks, the instance filled slot by slot) which takes what it can as
it stands and leaves everything else to the generic path, which decides and names the field
(docs/wire-contract.md, "How a message is checked").

Pure Python, no I/O.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import inspect
import math
import re
import sys
import threading
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from typing import Annotated, Any, ClassVar, TypeVar

import msgpack

from . import keys
from .clock import Clock

__all__ = [
    "DEFAULT_MAX_STR_LEN",
    "MAX_ARRAY_LEN",
    "MAX_MAP_LEN",
    "MAX_PAYLOAD",
    "SUPPORTED_MAJOR",
    "WIRE",
    "WIRE_VERSION",
    "FieldSpec",
    "Header",
    "HeaderCounter",
    "Limits",
    "Message",
    "WireError",
    "bounded",
    "check_version",
    "decode",
    "decode_any",
    "decode_key",
    "decode_key_unpacked",
    "encode",
    "generic_decoding",
    "key_of",
    "message_type",
    "register",
    "registered",
    "schema",
    "sized",
]

WIRE_VERSION = "1.2.0"
"""Version this code speaks, stamped into every header (1.1.0: ``OrderEdge.trajectory``; 1.2.0:
``Pose.map_began``, ``RobotFrame.began``, ``MapSnapshot.began`` and ``MapUpdate.began``)."""

SUPPORTED_MAJOR = 1
"""Decode accepts any ``1.x.y``; any other major version is rejected."""

MAX_PAYLOAD = 256 * 1024
"""Default limit on an encoded message, checked before unpacking (and on encode)."""

MAX_ARRAY_LEN = 65_536
"""msgpack unpack limit on any array (schema ``max_len`` limits are usually far lower)."""

MAX_MAP_LEN = 1_024
"""msgpack unpack limit on any map (maps are only ever structs)."""

DEFAULT_MAX_STR_LEN = 1_024
"""``str`` fields without an explicit ``max_len`` hold at most this many characters."""

WIRE = "fleetlink.wire"
"""Key for ``dataclasses.field(metadata={WIRE: Limits(...)})``."""

_INT_MIN = -(2**63)
_INT_MAX = 2**64 - 1  # msgpack integers are int64 or uint64
_VERSION_RE = re.compile(r"(0|[1-9][0-9]{0,8})\.(0|[1-9][0-9]{0,8})\.(0|[1-9][0-9]{0,8})")
_MAX_SHOWN = 40
_CHECK_CACHE_SIZE = 4_096


class WireError(ValueError):
    """A message that breaks the contract. ``reason`` is ``"<field>: <problem>"``.

    ``field`` is a dotted path (``header.version``, ``errors[3]``), ``"payload"`` for problems with
    the bytes as a whole, or ``"topic"``/``"key"`` for addressing problems.
    """

    def __init__(self, problem: str, field: str = "") -> None:
        self.problem = problem
        self.field = field
        self.reason = f"{field}: {problem}" if field else problem
        super().__init__(self.reason)

    def under(self, parent: str) -> WireError:
        """The same error, seen from the struct or list containing ``field``."""
        if not self.field:
            path = parent
        elif self.field.startswith("["):
            path = parent + self.field
        else:
            path = f"{parent}.{self.field}"
        return WireError(self.problem, path)


def _show(value: object) -> str:
    text = repr(value)
    return text if len(text) <= _MAX_SHOWN else text[: _MAX_SHOWN - 3] + "..."


def _tname(value: object) -> str:
    return "nil" if value is None else type(value).__name__


# --------------------------------------------------------------------------------------------------
# Constraints


@dataclasses.dataclass(frozen=True, slots=True)
class Limits:
    """Constraints on one value.

    ``ge``/``le``: inclusive bounds for int and float. ``max_len``: characters of a str, bytes of
    a bytes, items of a list/tuple. ``item``: limits applied to every item of a list/tuple.
    ``check``: extra validator for the decoded value; raises ValueError (its message becomes the
    problem). It must be a pure function of the value: string values that passed are cached.
    """

    ge: float | None = None
    le: float | None = None
    max_len: int | None = None
    item: Limits | None = None
    check: Callable[[Any], object] | None = None

    def over(self, inner: Limits) -> Limits:
        """These limits, falling back to ``inner`` for anything unset here."""
        return Limits(
            ge=inner.ge if self.ge is None else self.ge,
            le=inner.le if self.le is None else self.le,
            max_len=inner.max_len if self.max_len is None else self.max_len,
            item=inner.item if self.item is None else self.item,
            check=inner.check if self.check is None else self.check,
        )


_NO_LIMITS = Limits()


def bounded(lo: float | None = None, hi: float | None = None) -> Limits:
    """Inclusive range ``lo <= value <= hi`` for an int or float (either end may be open)."""
    if lo is not None and hi is not None and lo > hi:
        raise ValueError(f"bounded({lo}, {hi}): empty range")
    return Limits(ge=lo, le=hi)


def sized(max_len: int, item: Limits | None = None) -> Limits:
    """At most ``max_len`` characters/bytes/items; ``item`` constrains each list/tuple item."""
    if max_len < 0:
        raise ValueError(f"sized({max_len}): negative length")
    return Limits(max_len=max_len, item=item)


def check_version(version: object) -> str:
    """Return ``version`` if it is ``MAJOR.MINOR.PATCH`` with a supported major, else ValueError."""
    if not isinstance(version, str):
        raise ValueError(f"expected a string, got {_tname(version)}")
    match = _VERSION_RE.fullmatch(version)
    if match is None:
        raise ValueError(f"malformed version {_show(version)} (expected MAJOR.MINOR.PATCH)")
    if int(match.group(1)) != SUPPORTED_MAJOR:
        raise ValueError(f"unknown major version in {version!r} (this side speaks {SUPPORTED_MAJOR}.x.y)")
    return version


def _check_sender_id(sender: object) -> str:
    return keys.check_id(sender, "sender id")


# --------------------------------------------------------------------------------------------------
# Header and message base


@dataclasses.dataclass(frozen=True, slots=True)
class Header:
    """On every message (VDA 5050 style). ``headerId`` counts per topic (and robot) at the sender."""

    headerId: Annotated[int, bounded(0, _INT_MAX)]  # VDA 5050 name, hence camelCase
    timestamp: Annotated[float, bounded(0.0)]  # seconds since the Unix epoch
    version: Annotated[str, Limits(max_len=32, check=check_version)]
    robot: Annotated[str, Limits(max_len=64, check=keys.check_robot_id)]
    sender: Annotated[str, Limits(max_len=64, check=_check_sender_id)]


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class Message:
    """Base of every top-level message. Subclasses set ``TOPIC`` and add fields."""

    TOPIC: ClassVar[str]
    header: Header


M = TypeVar("M", bound=Message)


# --------------------------------------------------------------------------------------------------
# Compiled codecs

_Fn = Callable[[Any], Any]


@dataclasses.dataclass(frozen=True, slots=True)
class _Codec:
    dec: _Fn  # wire value -> Python value, raises WireError
    enc: _Fn  # Python value -> wire value, raises WireError


@dataclasses.dataclass(frozen=True, slots=True)
class FieldSpec:
    """One field of a compiled schema: its name, its type (``Annotated`` stripped) and limits."""

    name: str
    type: Any
    limits: Limits


class _Struct:
    """Codec for one dataclass, built once.

    ``dec`` runs the decoder generated for the class (``_generate``: straight-line code, every
    check inlined); on anything it does not accept as it stands it re-runs the generic,
    field-by-field path (``_dec_slow``), which decides: it accepts what the generated code would
    have and finds and names the offending field. ``enc`` tries one comprehension over the fields,
    and the field-by-field path if anything is wrong.
    """

    __slots__ = ("cls", "codec", "dec_fields", "defaults", "enc_fields", "fast", "n", "names", "source", "specs")

    def __init__(self, cls: type[Any], specs: tuple[FieldSpec, ...], codecs: tuple[_Codec, ...]) -> None:
        self.cls = cls
        self.specs = specs
        self.n = len(specs)
        self.names = frozenset(s.name for s in specs)
        # Fields with a default may be left out: a minor version adds fields only with one, so a
        # sender of an earlier 1.x (an agent not yet upgraded, a recording) is still understood.
        self.defaults = {
            f.name: f.default for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING and f.init
        }
        self.dec_fields = tuple((s.name, c.dec) for s, c in zip(specs, codecs, strict=True))
        self.enc_fields = tuple((s.name, c.enc) for s, c in zip(specs, codecs, strict=True))
        self.fast, self.source = _generate(cls, specs)
        self.codec = _Codec(self.dec, self.enc)

    def dec(self, value: Any) -> Any:
        if _generated:
            try:
                return self.fast(value)
            except Exception:
                pass  # the generic path decides, and names the offending field
        return self._dec_slow(value)

    def _dec_slow(self, value: Any) -> Any:
        if type(value) is not dict:
            raise WireError(f"expected a map, got {_tname(value)}")
        kwargs: dict[str, Any] = {}
        present = 0
        for name, dec in self.dec_fields:
            try:
                raw = value[name]
            except KeyError:
                if name in self.defaults:
                    kwargs[name] = self.defaults[name]
                    continue
                raise WireError("missing field", name) from None
            present += 1
            try:
                kwargs[name] = dec(raw)
            except WireError as exc:
                raise exc.under(name) from None
        if len(value) != present:
            extra = [k for k in value if k not in self.names]
            more = f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""
            raise WireError(f"unknown field in {self.cls.__name__}{more}", _field_name(extra[0]))
        try:
            return self.cls(**kwargs)
        except Exception as exc:  # a __post_init__ check; decode must raise only WireError
            raise WireError(f"rejected by {self.cls.__name__}: {exc}") from None

    def enc(self, value: Any) -> dict[str, Any]:
        if isinstance(value, self.cls):
            try:
                return {name: enc(getattr(value, name)) for name, enc in self.enc_fields}
            except WireError:
                pass  # the slow path raises it again, naming the field
        return self._enc_slow(value)

    def _enc_slow(self, value: Any) -> dict[str, Any]:
        if not isinstance(value, self.cls):
            raise WireError(f"expected {self.cls.__name__}, got {_tname(value)}")
        out: dict[str, Any] = {}
        for name, enc in self.enc_fields:
            try:
                out[name] = enc(getattr(value, name))
            except WireError as exc:
                raise exc.under(name) from None
        return out


def _field_name(k: object) -> str:
    return k if isinstance(k, str) and k.isprintable() and len(k) <= _MAX_SHOWN else _show(k)


_STRUCTS: dict[type[Any], _Struct] = {}
_COMPILING: set[type[Any]] = set()
_LOCK = threading.RLock()


def _struct(cls: type[Any]) -> _Struct:
    found = _STRUCTS.get(cls)
    if found is not None:
        return found
    with _LOCK:
        found = _STRUCTS.get(cls)
        if found is None:
            found = _compile_struct(cls)
            _STRUCTS[cls] = found
        return found


def _compile_struct(cls: type[Any]) -> _Struct:
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"{cls!r} is not a dataclass")
    if cls in _COMPILING:
        raise TypeError(f"{cls.__name__} refers to itself; recursive messages are not supported")
    _COMPILING.add(cls)
    try:
        hints = typing.get_type_hints(cls, include_extras=True)
        specs: list[FieldSpec] = []
        codecs: list[_Codec] = []
        for f in dataclasses.fields(cls):
            meta = f.metadata.get(WIRE, _NO_LIMITS)
            if not isinstance(meta, Limits):
                raise TypeError(f"{cls.__name__}.{f.name}: metadata[{WIRE!r}] must be a Limits")
            tp, limits = _unwrap(hints[f.name], meta)
            where = f"{cls.__name__}.{f.name}"
            codecs.append(_compile(tp, limits, where))
            specs.append(FieldSpec(f.name, tp, limits))
        return _Struct(cls, tuple(specs), tuple(codecs))
    finally:
        _COMPILING.discard(cls)


def _unwrap(tp: Any, outer: Limits) -> tuple[Any, Limits]:
    """Strip ``Annotated``, merging its Limits under ``outer``."""
    limits = outer
    while typing.get_origin(tp) is Annotated:
        base, *extras = typing.get_args(tp)
        for extra in extras:
            if isinstance(extra, Limits):
                limits = limits.over(extra)
        tp = base
    return tp, limits


def _allow(limits: Limits, where: str, kind: str, *allowed: str) -> None:
    for name in ("ge", "le", "max_len", "item", "check"):
        if name not in allowed and getattr(limits, name) is not None:
            raise TypeError(f"{where}: limit {name!r} does not apply to {kind}")


def _checker(check: Callable[[Any], object]) -> tuple[Callable[[Any], None], set[str]]:
    """``run(value)``: ``check`` with its failure as a WireError, and the set of strings that
    passed (ids and versions repeat on every message: each is checked once)."""
    passed: set[str] = set()

    def run(value: Any) -> None:
        if type(value) is str and value in passed:
            return
        try:
            check(value)
        except Exception as exc:
            raise WireError(str(exc) or type(exc).__name__) from None
        if type(value) is str and len(passed) < _CHECK_CACHE_SIZE:
            passed.add(value)

    return run, passed


def _with_check(codec: _Codec, check: Callable[[Any], object] | None) -> _Codec:
    if check is None:
        return codec
    inner_dec, inner_enc = codec.dec, codec.enc
    run, _ = _checker(check)

    def dec(value: Any) -> Any:
        out = inner_dec(value)
        run(out)
        return out

    def enc(value: Any) -> Any:
        out = inner_enc(value)
        run(out)
        return out

    return _Codec(dec, enc)


def _range_text(lo: float | None, hi: float | None) -> str:
    return f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"


def _compile(tp: Any, limits: Limits, where: str) -> _Codec:
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        return _compile_optional(tp, limits, where)
    if origin is list or origin is tuple:
        return _compile_sequence(tp, origin, limits, where)
    if origin is not None:
        raise TypeError(f"{where}: unsupported type {tp!r}")
    if tp is bool:
        _allow(limits, where, "bool", "check")
        return _with_check(_Codec(_dec_bool, _dec_bool), limits.check)
    if tp is int:
        _allow(limits, where, "int", "ge", "le", "check")
        return _with_check(_int_codec(limits.ge, limits.le), limits.check)
    if tp is float:
        _allow(limits, where, "float", "ge", "le", "check")
        return _with_check(_float_codec(limits.ge, limits.le), limits.check)
    if tp is str:
        _allow(limits, where, "str", "max_len", "check")
        max_len = DEFAULT_MAX_STR_LEN if limits.max_len is None else limits.max_len
        return _with_check(_str_codec(max_len), limits.check)
    if tp is bytes:
        _allow(limits, where, "bytes", "max_len", "check")
        max_bytes = MAX_PAYLOAD if limits.max_len is None else limits.max_len
        return _with_check(_bytes_codec(max_bytes), limits.check)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        _allow(limits, where, "an enum", "check")
        return _with_check(_enum_codec(tp, where), limits.check)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        _allow(limits, where, "a struct", "check")
        return _with_check(_struct(tp).codec, limits.check)
    raise TypeError(f"{where}: unsupported type {tp!r}")


def _compile_optional(tp: Any, limits: Limits, where: str) -> _Codec:
    args = typing.get_args(tp)
    present = [a for a in args if a is not type(None)]
    if len(args) != 2 or len(present) != 1:
        raise TypeError(f"{where}: only Optional unions (X | None) are supported, got {tp!r}")
    inner_tp, inner_limits = _unwrap(present[0], limits)
    inner = _compile(inner_tp, inner_limits, where)
    inner_dec, inner_enc = inner.dec, inner.enc

    def dec(value: Any) -> Any:
        return None if value is None else inner_dec(value)

    def enc(value: Any) -> Any:
        return None if value is None else inner_enc(value)

    return _Codec(dec, enc)


def _compile_sequence(tp: Any, origin: Any, limits: Limits, where: str) -> _Codec:
    args = typing.get_args(tp)
    if origin is tuple:
        if len(args) != 2 or args[1] is not Ellipsis:
            raise TypeError(f"{where}: only variable-length tuples (tuple[X, ...]) are supported")
    elif len(args) != 1:
        raise TypeError(f"{where}: list needs one item type")
    _allow(limits, where, "a list", "max_len", "item", "check")
    if limits.max_len is None:
        raise TypeError(f"{where}: a list/tuple field needs a max_len (use sized(n))")
    max_len = limits.max_len
    item_tp, item_limits = _unwrap(args[0], limits.item or _NO_LIMITS)
    item = _compile(item_tp, item_limits, f"{where}[]")
    item_dec, item_enc = item.dec, item.enc
    make = tuple if origin is tuple else list

    def dec(value: Any) -> Any:
        if type(value) is not list:
            raise WireError(f"expected an array, got {_tname(value)}")
        if len(value) > max_len:
            raise WireError(f"{len(value)} items, more than the limit of {max_len}")
        try:
            return make([item_dec(x) for x in value])
        except WireError:
            _locate(item_dec, value)
            raise

    def enc(value: Any) -> Any:
        if not isinstance(value, (list, tuple)):
            raise WireError(f"expected a list or tuple, got {_tname(value)}")
        if len(value) > max_len:
            raise WireError(f"{len(value)} items, more than the limit of {max_len}")
        try:
            return [item_enc(x) for x in value]
        except WireError:
            _locate(item_enc, value)
            raise

    return _with_check(_Codec(dec, enc), limits.check)


def _locate(fn: _Fn, items: list[Any] | tuple[Any, ...]) -> None:
    """Re-run a failed item conversion one by one to report the failing index (error path only)."""
    for i, x in enumerate(items):
        try:
            fn(x)
        except WireError as exc:
            raise exc.under(f"[{i}]") from None


def _dec_bool(value: Any) -> bool:
    if type(value) is not bool:
        raise WireError(f"expected a bool, got {_tname(value)}")
    return value


def _int_codec(ge: float | None, le: float | None) -> _Codec:
    lo = _INT_MIN if ge is None or not math.isfinite(ge) else max(_INT_MIN, math.ceil(ge))
    hi = _INT_MAX if le is None or not math.isfinite(le) else min(_INT_MAX, math.floor(le))
    span = _range_text(ge, le)

    def dec(value: Any) -> int:
        if type(value) is not int:
            raise WireError(f"expected an integer, got {_tname(value)}")
        if value < lo or value > hi:
            raise WireError(f"{value} out of range {span}")
        return value

    def enc(value: Any) -> int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise WireError(f"expected an integer, got {_tname(value)}")
        return dec(int(value))

    return _Codec(dec, enc)


def _float_codec(ge: float | None, le: float | None) -> _Codec:
    lo = -math.inf if ge is None else float(ge)
    hi = math.inf if le is None else float(le)
    span = _range_text(ge, le)
    isfinite = math.isfinite

    def dec(value: Any) -> float:
        kind = type(value)
        if kind is not float:
            if kind is not int:
                raise WireError(f"expected a number, got {_tname(value)}")
            value = float(value)  # msgpack ints are at most 64-bit, so this cannot overflow
        if not isfinite(value):
            raise WireError(f"non-finite number {value!r}")
        if value < lo or value > hi:
            raise WireError(f"{value!r} out of range {span}")
        result: float = value
        return result

    def enc(value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise WireError(f"expected a number, got {_tname(value)}")
        try:
            number = float(value)
        except OverflowError:
            raise WireError(f"integer {_show(value)} too large for a float") from None
        return dec(number)

    return _Codec(dec, enc)


def _str_codec(max_len: int) -> _Codec:
    def dec(value: Any) -> str:
        if type(value) is not str:
            raise WireError(f"expected a string, got {_tname(value)}")
        if len(value) > max_len:
            raise WireError(f"string of {len(value)} characters, more than the limit of {max_len}")
        return value

    def enc(value: Any) -> str:
        if not isinstance(value, str):
            raise WireError(f"expected a string, got {_tname(value)}")
        return dec(str(value))

    return _Codec(dec, enc)


def _bytes_codec(max_len: int) -> _Codec:
    def dec(value: Any) -> bytes:
        if type(value) is not bytes:
            raise WireError(f"expected bytes, got {_tname(value)}")
        if len(value) > max_len:
            raise WireError(f"{len(value)} bytes, more than the limit of {max_len}")
        return value

    def enc(value: Any) -> bytes:
        if not isinstance(value, (bytes, bytearray, memoryview)):
            raise WireError(f"expected bytes, got {_tname(value)}")
        return dec(bytes(value))

    return _Codec(dec, enc)


def _enum_codec(cls: type[enum.Enum], where: str) -> _Codec:
    members: dict[str, enum.Enum] = {}
    for member in cls:
        if not isinstance(member.value, str):
            raise TypeError(f"{where}: enum {cls.__name__} must have str values, {member!r} does not")
        members[str(member.value)] = member
    allowed = ", ".join(repr(v) for v in members)

    def dec(value: Any) -> enum.Enum:
        if type(value) is not str:
            raise WireError(f"expected a string, got {_tname(value)}")
        member = members.get(value)
        if member is None:
            raise WireError(f"{_show(value)} is not one of {allowed}")
        return member

    def enc(value: Any) -> str:
        if isinstance(value, cls):
            return str(value.value)
        if isinstance(value, str) and value in members:
            return value
        raise WireError(f"expected {cls.__name__}, got {_show(value)}")

    return _Codec(dec, enc)


# --------------------------------------------------------------------------------------------------
# Generated decoders: one function per dataclass, written once when it is compiled


class _Fallback(Exception):
    """Raised by a generated decoder for anything it does not accept as it stands."""


_generated = True
"""Decode through the generated functions (False: the generic path alone, ``generic_decoding``)."""

_FLOAT_MAX = sys.float_info.max


@contextlib.contextmanager
def generic_decoding() -> Iterator[None]:
    """Within this block, decode with the generic field-by-field path only, as before the decoders
    were generated: the reference that tests hold the generated ones to. Not for concurrent use."""
    global _generated
    before, _generated = _generated, False
    try:
        yield
    finally:
        _generated = before


class _Writer:
    """Source text of one generated decoder and the values it refers to."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.env: dict[str, Any] = {"_Fallback": _Fallback}
        self._count = 0

    def name(self, hint: str) -> str:
        self._count += 1
        return f"{hint}{self._count}"

    def const(self, value: Any, hint: str) -> str:
        name = self.name(f"_{hint}")
        self.env[name] = value
        return name

    def line(self, indent: int, text: str) -> None:
        self.lines.append("    " * indent + text)

    def value(self, tp: Any, limits: Limits, v: str, indent: int) -> None:
        """Lines that check the wire value in local ``v`` against ``tp`` and ``limits`` and leave
        its decoded value in ``v``, or raise; mirrors ``_compile`` case by case."""
        origin = typing.get_origin(tp)
        if origin is typing.Union or origin is types.UnionType:
            inner = next(a for a in typing.get_args(tp) if a is not type(None))
            inner_tp, inner_limits = _unwrap(inner, limits)
            self.line(indent, f"if {v} is not None:")
            self.value(inner_tp, inner_limits, v, indent + 1)
            return
        fail = "raise _Fallback"
        if origin is list or origin is tuple:
            item_tp, item_limits = _unwrap(typing.get_args(tp)[0], limits.item or _NO_LIMITS)
            items, x = self.name("items"), self.name("x")
            self.line(indent, f"if type({v}) is not list or len({v}) > {limits.max_len!r}:")
            self.line(indent + 1, fail)
            self.line(indent, f"{items} = []")
            self.line(indent, f"for {x} in {v}:")
            self.value(item_tp, item_limits, x, indent + 1)
            self.line(indent + 1, f"{items}.append({x})")
            self.line(indent, f"{v} = tuple({items})" if origin is tuple else f"{v} = {items}")
        elif tp is bool:
            self.line(indent, f"if type({v}) is not bool:")
            self.line(indent + 1, fail)
        elif tp is int:
            ge, le = limits.ge, limits.le
            lo = _INT_MIN if ge is None or not math.isfinite(ge) else max(_INT_MIN, math.ceil(ge))
            hi = _INT_MAX if le is None or not math.isfinite(le) else min(_INT_MAX, math.floor(le))
            self.line(indent, f"if type({v}) is not int or not ({lo!r} <= {v} <= {hi!r}):")
            self.line(indent + 1, fail)
        elif tp is float:
            # One chained comparison within the finite floats: NaN, the infinities and anything out
            # of range all fail it.
            flo = max(-_FLOAT_MAX, -math.inf if limits.ge is None else float(limits.ge))
            fhi = min(_FLOAT_MAX, math.inf if limits.le is None else float(limits.le))
            self.line(indent, f"if type({v}) is not float:")
            self.line(indent + 1, f"if type({v}) is not int:")
            self.line(indent + 2, fail)
            self.line(indent + 1, f"{v} = float({v})")
            self.line(indent, f"if not ({flo!r} <= {v} <= {fhi!r}):")
            self.line(indent + 1, fail)
        elif tp is str or tp is bytes:
            default = DEFAULT_MAX_STR_LEN if tp is str else MAX_PAYLOAD
            max_len = default if limits.max_len is None else limits.max_len
            self.line(indent, f"if type({v}) is not {tp.__name__} or len({v}) > {max_len!r}:")
            self.line(indent + 1, fail)
        elif isinstance(tp, type) and issubclass(tp, enum.Enum):
            members = self.const({str(m.value): m for m in tp}, "members")
            self.line(indent, f"if type({v}) is not str:")
            self.line(indent + 1, fail)
            self.line(indent, f"{v} = {members}[{v}]")
        else:  # a nested dataclass: its own generated decoder
            self.line(indent, f"{v} = {self.const(_struct(tp).fast, 'struct')}({v})")
        if limits.check is not None:
            run, passed = _checker(limits.check)
            call = f"{self.const(run, 'check')}({v})"
            if tp is str:
                self.line(indent, f"if {v} not in {self.const(passed, 'passed')}:")
                self.line(indent + 1, call)
            else:
                self.line(indent, call)


def _slot_setters(cls: type[Any], names: tuple[str, ...]) -> list[Callable[[Any, Any], None]] | None:
    """Each field's slot ``__set__``, when making ``cls`` by filling its slots is what its
    dataclass ``__init__`` does: generated by ``dataclass`` (frozen, slotted, taking exactly the
    fields, no ``InitVar``), no ``__new__`` of its own. None otherwise: then the class is called."""
    params = getattr(cls, "__dataclass_params__", None)
    init = cls.__dict__.get("__init__")
    new: Any = getattr(cls, "__new__", None)
    if params is None or not params.frozen or init is None or new is not object.__new__:
        return None
    code = getattr(init, "__code__", None)
    if code is None or code.co_filename != "<string>":  # dataclass writes __init__ with exec
        return None
    try:
        taken = list(inspect.signature(init).parameters.values())[1:]
    except (TypeError, ValueError):
        return None
    if sorted(p.name for p in taken) != sorted(names) or any(
        p.kind not in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) for p in taken
    ):
        return None
    setters = []
    for name in names:
        slot = inspect.getattr_static(cls, name, None)
        if type(slot) is not types.MemberDescriptorType:
            return None
        setters.append(slot.__set__)
    return setters


def _generate(cls: type[Any], specs: tuple[FieldSpec, ...]) -> tuple[Callable[[Any], Any], str]:
    """The decoder of dataclass ``cls`` as one generated function, and its source.

    It checks what ``_Struct._dec_slow`` checks, inline: a map of exactly the fields (their
    count, then each by name), each value's type, range, length, enum value and ``check``; makes
    the instance as the dataclass's ``__init__`` would (its slots filled, then ``__post_init__``);
    and raises (``_Fallback``, ``KeyError``, a check's ``WireError``) on anything else, for the
    generic path to decide and name."""
    w = _Writer()
    names = tuple(s.name for s in specs)
    fn = f"decode_{cls.__name__}"
    w.line(0, f"def {fn}(value):")
    w.line(1, f"if type(value) is not dict or len(value) != {len(specs)}:")
    w.line(2, "raise _Fallback")
    local = [f"f{i}" for i in range(len(specs))]
    for v, spec in zip(local, specs, strict=True):
        w.line(1, f"{v} = value[{spec.name!r}]")
    for v, spec in zip(local, specs, strict=True):
        w.value(spec.type, spec.limits, v, 1)
    setters = _slot_setters(cls, names)
    made = w.const(cls, "cls")
    if setters is None:
        w.line(1, f"return {made}({', '.join(f'{n}={v}' for n, v in zip(names, local, strict=True))})")
    else:
        w.line(1, f"o = {w.const(object.__new__, 'new')}({made})")
        for v, setter in zip(local, setters, strict=True):
            w.line(1, f"{w.const(setter, 'set')}(o, {v})")
        if hasattr(cls, "__post_init__"):
            w.line(1, "o.__post_init__()")
        w.line(1, "return o")
    source = "\n".join(w.lines) + "\n"
    scope: dict[str, Any] = {}
    exec(compile(source, f"<fleetlink.wire decoder of {cls.__qualname__}>", "exec"), w.env, scope)
    decoder: Callable[[Any], Any] = scope[fn]
    return decoder, source


# --------------------------------------------------------------------------------------------------
# Registry


_REGISTRY: dict[str, type[Message]] = {}


def register(cls: type[M]) -> type[M]:
    """Class decorator: compile ``cls``'s schema and make it decodable by ``TOPIC``.

    Raises TypeError for an unsupported schema and ValueError for a bad or duplicate TOPIC.
    """
    if not (isinstance(cls, type) and issubclass(cls, Message) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"{cls!r} must be a dataclass deriving from Message")
    topic = getattr(cls, "TOPIC", None)
    if not isinstance(topic, str):
        raise TypeError(f"{cls.__name__} needs a TOPIC class attribute (a str)")
    if topic != keys.TRUTH_TOPIC:
        keys.check_topic(topic)
    _struct(cls)
    with _LOCK:
        existing = _REGISTRY.get(topic)
        if existing is not None and existing is not cls:
            raise ValueError(f"topic {topic!r} is already registered to {existing.__name__}")
        _REGISTRY[topic] = cls
    return cls


_builtins_loaded = False


def _load_builtin_messages() -> None:
    global _builtins_loaded
    if not _builtins_loaded:
        # Imported lazily: messages imports this module.
        from . import messages  # noqa: F401

        _builtins_loaded = True


def registered() -> Mapping[str, type[Message]]:
    """Read-only view of TOPIC -> message class (includes every message in shared.messages)."""
    _load_builtin_messages()
    return types.MappingProxyType(_REGISTRY)


def message_type(topic: str) -> type[Message]:
    """The class registered for ``topic``; KeyError if none."""
    _load_builtin_messages()
    return _REGISTRY[topic]


def schema(cls: type[Any]) -> tuple[FieldSpec, ...]:
    """The compiled fields of a message (or nested struct) class, in wire order."""
    return _struct(cls).specs


def key_of(msg: Message) -> str:
    """Where ``msg`` is published: ``fleetlink/v1/<header.robot>/<TOPIC>``, followed by
    ``/<header.sender>`` for what people publish (``keys.SENDER_TOPICS``), or its truth key."""
    if msg.TOPIC == keys.TRUTH_TOPIC:
        return keys.truth_key(msg.header.robot)
    if msg.TOPIC in keys.SENDER_TOPICS:
        return keys.sender_key(msg.header.robot, msg.TOPIC, msg.header.sender)
    if msg.TOPIC in keys.INDEXED_TOPICS:
        return keys.indexed_key(msg.header.robot, msg.TOPIC, msg.index)  # type: ignore[attr-defined]
    return keys.key(msg.header.robot, msg.TOPIC)


# --------------------------------------------------------------------------------------------------
# Encode / decode


def encode(msg: Message, *, max_payload: int = MAX_PAYLOAD) -> bytes:
    """Validate ``msg`` against its schema and pack it. Raises WireError if it breaks the contract."""
    if not isinstance(msg, Message):
        raise WireError(f"expected a Message, got {_tname(msg)}", "payload")
    data: bytes = msgpack.packb(_struct(type(msg)).enc(msg), use_bin_type=True)
    if len(data) > max_payload:
        raise WireError(f"encoded size {len(data)} bytes exceeds the limit of {max_payload}", "payload")
    return data


def _unpack(data: object, max_payload: int) -> Any:
    if isinstance(data, memoryview):
        size = data.nbytes
    elif isinstance(data, (bytes, bytearray)):
        size = len(data)
    else:
        raise WireError(f"expected bytes, got {_tname(data)}", "payload")
    if size > max_payload:
        raise WireError(f"{size} bytes exceeds the limit of {max_payload}", "payload")
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_str_len=max_payload,
            max_bin_len=max_payload,
            max_array_len=MAX_ARRAY_LEN,
            max_map_len=MAX_MAP_LEN,
            max_ext_len=0,
        )
    except Exception as exc:
        raise WireError(f"not valid msgpack ({type(exc).__name__}: {_show(str(exc))})", "payload") from None


def _decode_obj(cls: type[M], obj: Any) -> M:
    struct = _struct(cls)
    if type(obj) is not dict:
        raise WireError(f"expected a map, got {_tname(obj)}", "payload")
    # Check the version first: a message from another major version may have any shape.
    header = obj.get("header")
    if type(header) is dict:
        version = header.get("version", WIRE_VERSION)
        if version != WIRE_VERSION:
            try:
                check_version(version)
            except ValueError as exc:
                raise WireError(str(exc), "header.version") from None
    try:
        msg = struct.dec(obj)
    except WireError:
        raise
    except Exception as exc:  # never expected; keeps the "only WireError" promise
        raise WireError(f"internal error while validating ({type(exc).__name__}: {exc})", "payload") from None
    result: M = msg
    return result


def decode(expected: type[M], data: bytes, *, max_payload: int = MAX_PAYLOAD) -> M:
    """Unpack and validate a message of type ``expected``. Raises only WireError for bad data.

    (A TypeError for an ``expected`` that is not a valid schema is a programming error.)
    """
    _struct(expected)
    return _decode_obj(expected, _unpack(data, max_payload))


def decode_any(topic: str, data: bytes, *, max_payload: int = MAX_PAYLOAD) -> Message:
    """Decode a message whose class is looked up by ``topic``. Raises only WireError."""
    _load_builtin_messages()
    cls = _REGISTRY.get(topic) if isinstance(topic, str) else None
    if cls is None:
        raise WireError(f"no message registered for topic {_show(topic)}", "topic")
    return _decode_obj(cls, _unpack(data, max_payload))


def decode_key(key_expr: str, data: bytes, *, max_payload: int = MAX_PAYLOAD) -> Message:
    """Decode a message received on ``key_expr`` and check that its header agrees with the key:
    ``header.robot`` with the robot, and for ``keys.SENDER_TOPICS`` ``header.sender`` with the
    sender segment (which the transport's access control ties to the login; a key without one is
    refused).

    Accepts ordinary keys and truth keys. Raises only WireError.
    """
    return decode_key_unpacked(key_expr, data, max_payload=max_payload)[0]


def decode_key_unpacked(key_expr: str, data: bytes, *, max_payload: int = MAX_PAYLOAD) -> tuple[Message, Any]:
    """``decode_key``, and the unpacked msgpack value it validated (plain dicts and lists, not to be
    changed): for a receiver that also needs the message's wire form (the flight recorder's JSON,
    shared/wire_json.py) without unpacking it twice. Raises only WireError."""
    sender: str | None = None
    index: int | None = None
    try:
        if keys.is_truth_key(key_expr):
            robot, topic = keys.parse_truth_key(key_expr), keys.TRUTH_TOPIC
        else:
            robot, topic = keys.parse_key(key_expr)
            topic, sender = keys.split_sender(topic)
            if sender is None:
                topic, index = keys.split_index(topic)
    except ValueError as exc:
        raise WireError(str(exc), "key") from None
    if sender is None and topic in keys.SENDER_TOPICS:
        raise WireError(
            f"a {topic!r} message must be published on {keys.PREFIX}/<robot>/{topic}/<sender>, not {_show(key_expr)}",
            "key",
        )
    if index is None and topic in keys.INDEXED_TOPICS:
        raise WireError(
            f"a {topic!r} message must be published on {keys.PREFIX}/<robot>/{topic}/<index>, not {_show(key_expr)}",
            "key",
        )
    _load_builtin_messages()
    cls = _REGISTRY.get(topic)
    if cls is None:
        raise WireError(f"no message registered for topic {_show(topic)}", "topic")
    obj = _unpack(data, max_payload)
    msg = _decode_obj(cls, obj)
    if msg.header.robot != robot:
        raise WireError(f"{msg.header.robot!r} does not match the key's robot {robot!r}", "header.robot")
    if sender is not None and msg.header.sender != sender:
        raise WireError(
            f"{msg.header.sender!r} does not match the key's sender {sender!r} (who published it)", "header.sender"
        )
    if index is not None and getattr(msg, "index", None) != index:
        raise WireError(f"index {getattr(msg, 'index', None)!r} does not match the key's {index}", "index")
    return msg, obj


# --------------------------------------------------------------------------------------------------
# Header stamping


class HeaderCounter:
    """Stamps headers for one sender: ``headerId`` counts from 0 per (robot, topic).

    ``robot`` is the default robot the messages are about (the agent's own id); pass
    ``robot=`` to ``header`` when one sender publishes for several robots (operator, simulator).
    Thread-safe.
    """

    def __init__(self, clock: Clock, *, robot: str, sender: str, version: str = WIRE_VERSION) -> None:
        self._clock = clock
        self._robot = keys.check_robot_id(robot)
        self._sender = _check_sender_id(sender)
        self._version = check_version(version)
        self._next: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()

    @property
    def robot(self) -> str:
        return self._robot

    @property
    def sender(self) -> str:
        return self._sender

    def header(self, topic: str, *, robot: str | None = None) -> Header:
        """A fresh header for the next message on ``topic``."""
        who = self._robot if robot is None else robot
        slot = (who, topic)
        with self._lock:
            if slot not in self._next:
                keys.check_robot_id(who)
                if topic != keys.TRUTH_TOPIC:
                    keys.check_topic(topic)
            header_id = self._next.get(slot, 0)
            self._next[slot] = header_id + 1
        return Header(
            headerId=header_id,
            timestamp=self._clock.wall(),
            version=self._version,
            robot=who,
            sender=self._sender,
        )

    def make(self, cls: type[M], /, **fields: Any) -> M:
        """``cls(header=<next header for cls.TOPIC>, **fields)`` for the default robot."""
        return cls(header=self.header(cls.TOPIC), **fields)

    def peek(self, topic: str, *, robot: str | None = None) -> int:
        """The headerId the next header on ``topic`` will get."""
        with self._lock:
            return self._next.get((self._robot if robot is None else robot, topic), 0)
