"""Reading TOML configuration with clear errors: every problem names the file, the key and the reason.

Plans, scenarios and robot configurations all read TOML through ``TomlReader`` so they refuse bad
input the same way: unknown keys (with the allowed ones listed), missing keys, wrong types,
non-finite numbers and out-of-range values.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["ConfigError", "TomlReader", "read_toml"]


class ConfigError(ValueError):
    """A configuration that cannot be used, with where and why."""


def read_toml(path: str | Path, error: type[ValueError] = ConfigError) -> dict[str, Any]:
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise error(f"{p}: cannot read: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise error(f"{p}: not UTF-8 text: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: not valid TOML: {exc}") from exc


class TomlReader:
    """Typed access to parsed TOML; ``where`` is the dotted path used in error messages."""

    def __init__(self, source: str, error: type[ValueError] = ConfigError) -> None:
        self.source = source
        self.error = error

    def fail(self, where: str, problem: str) -> ValueError:
        return self.error(f"{self.source}: {where}: {problem}")

    def keys(self, table: Mapping[str, Any], where: str, allowed: Iterable[str], required: Iterable[str] = ()) -> None:
        allowed_set, required_set = set(allowed), set(required)
        unknown = sorted(set(table) - allowed_set)
        if unknown:
            raise self.fail(where, f"unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed_set))}")
        missing = sorted(required_set - set(table))
        if missing:
            raise self.fail(where, f"missing key(s) {', '.join(missing)}")

    def number(self, v: object, where: str, lo: float | None = None, hi: float | None = None) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(where, f"expected a number, got {type(v).__name__} {v!r}")
        f = float(v)
        if not math.isfinite(f):
            raise self.fail(where, f"must be finite, got {f}")
        if lo is not None and f < lo:
            raise self.fail(where, f"must be >= {lo}, got {f}")
        if hi is not None and f > hi:
            raise self.fail(where, f"must be <= {hi}, got {f}")
        return f

    def integer(self, v: object, where: str, lo: int | None = None, hi: int | None = None) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(where, f"expected a whole number, got {type(v).__name__} {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.fail(where, f"must be between {lo} and {hi}, got {v}")
        return v

    def text(self, v: object, where: str, nonempty: bool = False) -> str:
        if not isinstance(v, str) or (nonempty and not v):
            raise self.fail(where, f"expected a {'non-empty ' if nonempty else ''}string, got {type(v).__name__} {v!r}")
        return v

    def flag(self, v: object, where: str) -> bool:
        if not isinstance(v, bool):
            raise self.fail(where, f"expected true or false, got {v!r}")
        return v

    def numbers(self, v: object, where: str, n: int, shape: str) -> tuple[float, ...]:
        if not isinstance(v, list) or len(v) != n:
            raise self.fail(where, f"expected {shape}, got {v!r}")
        return tuple(self.number(c, f"{where}[{k}]") for k, c in enumerate(v))

    def polygon(self, v: object, where: str) -> tuple[tuple[float, float], ...]:
        if not isinstance(v, list):
            raise self.fail(where, f"expected a list of [x, y] points, got {v!r}")
        if len(v) < 3:
            raise self.fail(where, f"a polygon needs at least 3 points, got {len(v)}")
        pts = [self.numbers(q, f"{where}[{k}]", 2, "[x, y]") for k, q in enumerate(v)]
        return tuple((p[0], p[1]) for p in pts)

    def tables(self, data: Mapping[str, Any], key: str) -> list[Mapping[str, Any]]:
        v = data.get(key, [])
        if not isinstance(v, list) or not all(isinstance(t, dict) for t in v):
            raise self.fail(key, f"expected an array of tables ([[{key}]])")
        return v

    def table(self, data: Mapping[str, Any], key: str) -> Mapping[str, Any]:
        v = data.get(key, {})
        if not isinstance(v, dict):
            raise self.fail(key, f"expected a table ([{key}])")
        return v
