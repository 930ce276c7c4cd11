"""One way to read TOML configuration: sections declared as dataclasses, one loader, clear errors.

Every configuration file (robot, uwb, console, scenario, plan) is a tree of frozen dataclasses.
A field's type says what the file must hold; ``Annotated[..., Setting(...)]`` adds bounds,
choices, a TOML key that differs from the attribute, a conversion and a one-line doc (the same
idea as ``shared/wire.py``'s ``Limits``)::

    @dataclass(frozen=True, slots=True)
    class Lidar:
        rate_hz: Annotated[float, Setting(lo=1.0, hi=20.0, doc="turns a second")] = 10.0
        mode: Literal["fast", "slow"] = "fast"

    @dataclass(frozen=True, slots=True)
    class Robot:
        name: Annotated[str, Setting(min_len=1)]                 # no default: required
        lidar: Lidar = field(default_factory=Lidar)              # a [table]
        duration: Annotated[float, Setting(key="duration_s", lo=0.0)] = 60.0

        def validate(self) -> None:                              # optional cross-field checks
            if ...: raise Invalid("lidar.mode", "why")

    robot = load("robot.toml", Robot)        # or loads(text, Robot) / parse(mapping, Robot)

Supported types: ``bool``, ``int`` (rejects bool and 2.5), ``float`` (accepts int; rejects bool,
NaN and inf), ``str``, ``Literal[...]`` and ``Enum`` (choices), ``X | None`` (absent: None),
nested dataclasses (tables), ``tuple[X, ...]`` / ``list[X]`` (arrays, arrays of tables),
``tuple[X, Y, Z]`` (fixed length), ``dict[str, X]`` (tables of named entries), ``Any``, and unions
of dataclasses told apart by their ``kind`` class attribute (``[[events]]`` with ``kind = ...``).

Every problem raises ``ConfigError`` (or the subclass given as ``error``) reading
``<file>: <dotted key>: <what was wrong>``, e.g. ``robots.toml: robots[2].lidar.rate_hz: must be
<= 20.0, got 50.0`` or ``robot.toml: limits.v_mx: unknown key (did you mean v_max?); allowed:
...``. The first problem found is reported; nothing is half-loaded. Pure Python; only ``load``
reads a file.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import math
import tomllib
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

__all__ = [
    "CONFIG_KIND",
    "ConfigError",
    "Invalid",
    "Setting",
    "describe",
    "load",
    "loads",
    "parse",
    "read_toml",
]

T = TypeVar("T")

CONFIG_KIND = "kind"
"""The key that picks a class from a union of dataclasses (each has a ``kind`` class attribute)."""

_MAX_SHOWN = 60  # characters of a bad value quoted in a message


class ConfigError(ValueError):
    """A configuration that cannot be used: ``<source>: <key>: <problem>``.

    ``source``, ``key`` and ``problem`` are kept for callers that want them apart (``key`` is
    ``""`` for the file as a whole).
    """

    def __init__(self, message: str, *, source: str = "", key: str = "", problem: str = "") -> None:
        super().__init__(message)
        self.source = source
        self.key = key
        self.problem = problem or message

    @classmethod
    def at(cls, source: str, key: str, problem: str) -> ConfigError:
        return cls(f"{source}: {key or 'top level'}: {problem}", source=source, key=key, problem=problem)


class Invalid(ValueError):
    """Raised by a ``validate()`` hook or a ``convert`` function: ``key`` is relative to the
    section being checked (``""``: the section itself; ``"robots[1].script"``: deeper)."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key}: {problem}" if key else problem)
        self.key = key
        self.problem = problem


@dataclasses.dataclass(frozen=True, slots=True)
class Setting:
    """What a field of a configuration dataclass accepts, beyond its type.

    ``key``: the TOML key when it differs from the attribute (``duration_s`` for ``duration``).
    ``lo``/``hi``: inclusive bounds of a number. ``choices``: the values a str/int may take.
    ``min_len``/``max_len``: characters of a str, items of an array or table.
    ``convert``: applied to the checked value; returns what is stored, raises ``ValueError`` (or
    ``Invalid``) whose text becomes the problem. ``read_as``: the type the file holds when it differs
    from the attribute's (``convert`` turns one into the other). ``what``: how to describe the
    expected value in a message (``"[x1, y1, x2, y2]"``). ``read``: False for fields the program
    fills in (never a key of the file). ``required``: the file must give it even though the
    dataclass has a default (for code that builds one by hand). ``doc``: one line for ``describe``.
    """

    key: str | None = None
    lo: float | None = None
    hi: float | None = None
    choices: tuple[Any, ...] | None = None
    min_len: int | None = None
    max_len: int | None = None
    convert: Callable[[Any], Any] | None = None
    read_as: Any = None
    what: str | None = None
    read: bool = True
    required: bool = False
    doc: str = ""

    def over(self, inner: Setting) -> Setting:
        """This setting, falling back to ``inner`` for anything unset here."""
        base = _NO_SETTING
        return Setting(
            **{
                f.name: getattr(inner if getattr(self, f.name) == getattr(base, f.name) else self, f.name)
                for f in dataclasses.fields(Setting)
            }
        )


_NO_SETTING = Setting()


# -- reading ---------------------------------------------------------------------------------------


def read_toml(path: str | Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """A TOML file as a dict; ``error`` naming the file when it cannot be read or parsed."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise error(f"{p}: cannot read: {exc}", source=str(p), problem=f"cannot read: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise error(f"{p}: not UTF-8 text: {exc}", source=str(p), problem=f"not UTF-8 text: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: not valid TOML: {exc}", source=str(p), problem=f"not valid TOML: {exc}") from exc


def load(path: str | Path, schema: type[T], *, error: type[ConfigError] = ConfigError) -> T:
    """Read the TOML file at ``path`` into ``schema``; messages name the file."""
    return parse(read_toml(path, error), schema, source=str(path), error=error)


def loads(text: str, schema: type[T], *, source: str = "<text>", error: type[ConfigError] = ConfigError) -> T:
    """Read TOML text into ``schema``; messages name ``source``."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error.at(source, "", f"not valid TOML: {exc}") from exc
    return parse(data, schema, source=source, error=error)


def parse(
    data: Mapping[str, Any],
    schema: type[T],
    *,
    source: str = "<memory>",
    where: str = "",
    error: type[ConfigError] = ConfigError,
) -> T:
    """Check decoded TOML against ``schema`` and build it; ``where`` prefixes every key (a table
    read on its own, e.g. ``"mqtt"``)."""
    try:
        out: T = _read(schema, _NO_SETTING, data, where)
    except Invalid as exc:
        raise error.at(source, exc.key, exc.problem) from None
    return out


def _join(path: str, key: str) -> str:
    if not key:
        return path
    if not path:
        return key
    return f"{path}{key}" if key.startswith("[") else f"{path}.{key}"


def _got(value: object) -> str:
    if isinstance(value, dict):
        return "a table"
    shown = repr(value)
    if len(shown) > _MAX_SHOWN:
        shown = shown[: _MAX_SHOWN - 3] + "..."
    return shown if isinstance(value, list) else f"{type(value).__name__} {shown}"


def _num(v: float) -> str:
    return str(v)


def _suggest(word: str, known: Iterable[str]) -> str:
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _unwrap(tp: Any, outer: Setting) -> tuple[Any, Setting]:
    """Strip ``Annotated``, merging its Setting under ``outer``."""
    setting = outer
    while typing.get_origin(tp) is Annotated:
        base, *extras = typing.get_args(tp)
        for extra in extras:
            if isinstance(extra, Setting):
                setting = setting.over(extra)
        tp = base
    return tp, setting


def _read(tp: Any, setting: Setting, value: Any, path: str) -> Any:
    tp, setting = _unwrap(tp, setting)
    if setting.read_as is not None:
        tp, setting = _unwrap(setting.read_as, dataclasses.replace(setting, read_as=None))
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        present = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(present) == 1:
            return _read(present[0], setting, value, path)  # None is "absent": TOML has no null
    out = _read_type(tp, setting, value, path)
    if isinstance(out, (int, float)):
        if setting.lo is not None and out < setting.lo:
            raise Invalid(path, f"must be >= {_num(setting.lo)}, got {_num(out)}{_expected(setting)}")
        if setting.hi is not None and out > setting.hi:
            raise Invalid(path, f"must be <= {_num(setting.hi)}, got {_num(out)}{_expected(setting)}")
    if setting.choices is not None and out not in setting.choices:
        raise _not_a_choice(path, out, setting.choices)
    if setting.convert is not None:
        try:
            out = setting.convert(out)
        except Invalid as exc:
            raise Invalid(_join(path, exc.key), exc.problem) from None
        except (ValueError, TypeError) as exc:
            raise Invalid(path, str(exc)) from None
    return out


def _not_a_choice(path: str, value: object, choices: Iterable[Any]) -> Invalid:
    names = [str(c) for c in choices]
    hint = _suggest(value, names) if isinstance(value, str) else ""
    return Invalid(path, f"expected one of {', '.join(names)}, got {value!r}{hint}")


def _read_type(tp: Any, setting: Setting, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        return _read_tagged([a for a in typing.get_args(tp) if a is not type(None)], value, path)
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices or isinstance(value, bool) != any(isinstance(c, bool) for c in choices):
            raise _not_a_choice(path, value, choices)
        return value
    if origin in (tuple, list):
        return _read_array(tp, origin, setting, value, path)
    if origin in (dict, Mapping):
        return _read_named(tp, setting, value, path)
    if origin is not None:
        raise TypeError(f"{path}: unsupported configuration type {tp!r}")
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise Invalid(path, f"expected true or false, got {_got(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise Invalid(path, f"expected a whole number, got {_got(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise Invalid(path, f"expected {setting.what or 'a number'}, got {_got(value)}")
        f = float(value)
        if not math.isfinite(f):
            raise Invalid(path, f"must be finite, got {f}")
        return f
    if tp is str:
        if not isinstance(value, str):
            raise Invalid(path, f"expected {setting.what or 'a string'}, got {_got(value)}")
        if setting.min_len and len(value) < setting.min_len:
            raise Invalid(
                path, "must not be empty" if setting.min_len == 1 else f"at least {setting.min_len} characters"
            )
        if setting.max_len is not None and len(value) > setting.max_len:
            raise Invalid(path, f"at most {setting.max_len} characters, got {len(value)}")
        return value
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        for member in tp:
            if member.value == value:
                return member
        raise _not_a_choice(path, value, [m.value for m in tp])
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return _read_struct(tp, setting, value, path)
    raise TypeError(f"{path}: unsupported configuration type {tp!r}")


def _check_len(n: int, setting: Setting, path: str, noun: str) -> None:
    nouns = "entries" if noun == "entry" else f"{noun}s"
    if setting.min_len is not None and n < setting.min_len:
        many = noun if setting.min_len == 1 else nouns
        raise Invalid(path, f"needs at least {setting.min_len} {many}, got {n}{_expected(setting)}")
    if setting.max_len is not None and n > setting.max_len:
        raise Invalid(path, f"takes at most {setting.max_len} {nouns}, got {n}{_expected(setting)}")


def _expected(setting: Setting) -> str:
    return f"; expected {setting.what}" if setting.what else ""


def _read_array(tp: Any, origin: Any, setting: Setting, value: Any, path: str) -> Any:
    args = typing.get_args(tp)
    fixed = origin is tuple and not (len(args) == 2 and args[1] is Ellipsis)
    if fixed:
        what = setting.what or f"a list of {len(args)} values"
        if not isinstance(value, list) or len(value) != len(args):
            raise Invalid(path, f"expected {what}, got {_got(value)}")
        return tuple(_read(a, _NO_SETTING, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    item = args[0] if args else Any
    if not isinstance(value, list):
        item_tp, _ = _unwrap(item, _NO_SETTING)
        shape = "an array of tables" if _is_table_type(item_tp) else "a list"
        raise Invalid(path, f"expected {setting.what or shape}, got {_got(value)}")
    _check_len(len(value), setting, path, "item")
    items = [_read(item, _NO_SETTING, v, f"{path}[{i}]") for i, v in enumerate(value)]
    return tuple(items) if origin is tuple else items


def _is_table_type(tp: Any) -> bool:
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return True
    origin = typing.get_origin(tp)
    return (origin is typing.Union or origin is types.UnionType) and all(
        _is_table_type(a) for a in typing.get_args(tp) if a is not type(None)
    )


def _read_named(tp: Any, setting: Setting, value: Any, path: str) -> dict[str, Any]:
    args = typing.get_args(tp)
    item = args[1] if len(args) == 2 else Any
    if not isinstance(value, dict):
        raise Invalid(path, f"expected {setting.what or 'a table'}, got {_got(value)}")
    _check_len(len(value), setting, path, "entry")
    return {k: _read(item, _NO_SETTING, v, _join(path, k)) for k, v in value.items()}


@dataclasses.dataclass(frozen=True, slots=True)
class _Field:
    name: str  # the attribute
    key: str  # the TOML key
    tp: Any
    setting: Setting
    required: bool
    default: Any  # for describe(); dataclasses.MISSING when required


_FIELDS: dict[type[Any], tuple[_Field, ...]] = {}


def _fields_of(cls: type[Any]) -> tuple[_Field, ...]:
    found = _FIELDS.get(cls)
    if found is not None:
        return found
    hints = typing.get_type_hints(cls, include_extras=True)
    out: list[_Field] = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        _, setting = _unwrap(hints[f.name], _NO_SETTING)
        if not setting.read:
            continue
        required = setting.required or (f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING)
        default = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        out.append(_Field(f.name, setting.key or f.name, hints[f.name], setting, required, default))
    _FIELDS[cls] = tuple(out)
    return _FIELDS[cls]


def _read_struct(cls: type[Any], setting: Setting, value: Any, path: str, tag: str | None = None) -> Any:
    if not isinstance(value, dict):
        raise Invalid(path, f"expected {setting.what or 'a table'}, got {_got(value)}")
    fields = _fields_of(cls)
    known = [f.key for f in fields] + ([tag] if tag else [])
    for k in value:
        if k not in known:
            allowed = ", ".join(sorted(f.key for f in fields))
            raise Invalid(_join(path, str(k)), f"unknown key{_suggest(str(k), known)}; allowed: {allowed}")
    kwargs: dict[str, Any] = {}
    for f in fields:
        if f.key not in value:
            if f.required:
                raise Invalid(_join(path, f.key), "missing required key")
            continue
        kwargs[f.name] = _read(f.tp, _NO_SETTING, value[f.key], _join(path, f.key))
    try:
        obj = cls(**kwargs)
        hook = getattr(obj, "validate", None)
        if callable(hook):
            hook()
    except Invalid as exc:
        raise Invalid(_join(path, exc.key), exc.problem) from None
    except (ValueError, TypeError) as exc:
        raise Invalid(path, str(exc)) from None
    return obj


def _read_tagged(classes: list[Any], value: Any, path: str) -> Any:
    by_kind: dict[str, type[Any]] = {}
    for c in classes:
        c, _ = _unwrap(c, _NO_SETTING)
        kind = getattr(c, CONFIG_KIND, None)
        if not (isinstance(c, type) and dataclasses.is_dataclass(c) and isinstance(kind, str)):
            raise TypeError(f"{path}: a union must be of dataclasses with a {CONFIG_KIND!r} class attribute")
        by_kind[kind] = c
    if not isinstance(value, dict):
        raise Invalid(path, f"expected a table, got {_got(value)}")
    if CONFIG_KIND not in value:
        raise Invalid(_join(path, CONFIG_KIND), f"missing required key (one of {', '.join(by_kind)})")
    kind = value[CONFIG_KIND]
    if kind not in by_kind:
        raise _not_a_choice(_join(path, CONFIG_KIND), kind, by_kind)
    return _read_struct(by_kind[kind], _NO_SETTING, value, path, tag=CONFIG_KIND)


# -- documentation ---------------------------------------------------------------------------------


def describe(schema: type[Any], prefix: str = "") -> list[str]:
    """One line per key of ``schema`` (nested tables as dotted keys): type, default, limits, doc."""
    lines: list[str] = []
    for f in _fields_of(schema):
        tp, setting = _unwrap(f.tp, f.setting)
        if setting.read_as is not None:
            tp, setting = _unwrap(setting.read_as, setting)
        key = _join(prefix, f.key)
        if isinstance(tp, type) and dataclasses.is_dataclass(tp) and not f.required:
            lines.extend(describe(tp, key))
            continue
        parts = [key, _type_name(tp)]
        parts.append("required" if f.required else f"default {_show_default(f.default)}")
        if setting.lo is not None or setting.hi is not None:
            lo = "-inf" if setting.lo is None else _num(setting.lo)
            hi = "inf" if setting.hi is None else _num(setting.hi)
            parts.append(f"in [{lo}, {hi}]")
        if setting.choices is not None:
            parts.append("one of " + ", ".join(str(c) for c in setting.choices))
        line = "  ".join(parts)
        lines.append(f"{line}  # {setting.doc}" if setting.doc else line)
    return lines


def _show_default(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if dataclasses.is_dataclass(v):
        return "{...}"
    if isinstance(v, enum.Enum):
        return repr(v.value)
    return repr(v) if not isinstance(v, tuple) else repr(list(v))


def _type_name(tp: Any) -> str:
    tp, _ = _unwrap(tp, _NO_SETTING)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union or origin is types.UnionType:
        present = [a for a in args if a is not type(None)]
        if len(present) == 1:
            return _type_name(present[0])
        return " | ".join(getattr(_unwrap(a, _NO_SETTING)[0], CONFIG_KIND, "?") for a in present)
    if origin is Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (tuple, list):
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            return "[" + ", ".join(_type_name(a) for a in args) + "]"
        item = _unwrap(args[0], _NO_SETTING)[0] if args else Any
        if _is_table_type(item):
            return f"[[{_type_name(item)}]]"
        return f"[{_type_name(item)}, ...]"
    if origin in (dict, Mapping):
        return f"{{name = {_type_name(args[1]) if len(args) == 2 else 'any'}}}"
    names = {bool: "bool", int: "int", float: "float", str: "string"}
    if tp in names:
        return names[tp]
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return " | ".join(repr(m.value) for m in tp)
    return getattr(tp, "__name__", str(tp))
