"""Zenoh login settings read from a ``[zenoh]`` table, one way for every process. Pure: no I/O
beyond reading a password file; sessions are opened in fleetlink.links.zenoh (``peer_config``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import TomlReader

__all__ = ["ZenohAuth", "read_zenoh_auth"]


@dataclass(frozen=True, slots=True)
class ZenohAuth:
    """How a session joins a (secured) site: mode, login, TLS files. ``peer_config(**auth.kwargs())``."""

    mode: str = "peer"  # "client" against a site router
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    root_ca: str | None = None  # the site CA for tls/ endpoints
    tls_cert: str | None = None
    tls_key: str | None = None

    def kwargs(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "username": self.username,
            "password": self.password,
            "root_ca": self.root_ca,
            "tls_cert": self.tls_cert,
            "tls_key": self.tls_key,
        }


def read_zenoh_auth(r: TomlReader, z: Mapping[str, Any], base_dir: str | Path | None = None) -> ZenohAuth:
    """The login part of a ``[zenoh]`` table (mode, username, password or password_file, root_ca,
    tls_cert + tls_key), with clear errors; relative paths are taken from ``base_dir``. One reader
    for every process (agent, UWB gateway), so a site's credentials look the same everywhere."""
    mode = r.text(z.get("mode", "peer"), "zenoh.mode")
    if mode not in ("peer", "client"):
        raise r.fail("zenoh.mode", f"must be 'peer' or 'client', got {mode!r}")

    def path(k: str) -> str | None:
        if k not in z:
            return None
        p = Path(r.text(z[k], f"zenoh.{k}", nonempty=True))
        if not p.is_absolute() and base_dir is not None:
            p = Path(base_dir) / p
        if not p.is_file():
            raise r.fail(f"zenoh.{k}", f"no such file {str(p)!r}")
        return str(p)

    user = r.text(z["username"], "zenoh.username", nonempty=True) if "username" in z else None
    password = r.text(z["password"], "zenoh.password", nonempty=True) if "password" in z else None
    password_file = path("password_file")
    if password is not None and password_file is not None:
        raise r.fail("zenoh", "give password or password_file, not both")
    if password_file is not None:
        try:
            password = Path(password_file).read_text(encoding="utf-8").strip("\r\n")
        except (OSError, UnicodeDecodeError) as exc:
            raise r.fail("zenoh.password_file", f"cannot read {password_file!r}: {exc}") from None
        if not password:
            raise r.fail("zenoh.password_file", f"{password_file!r} is empty")
    if (user is None) != (password is None):
        raise r.fail("zenoh", "username and password (or password_file) go together")
    cert, key = path("tls_cert"), path("tls_key")
    if (cert is None) != (key is None):
        raise r.fail("zenoh", "tls_cert and tls_key go together (both or neither)")
    return ZenohAuth(mode, user, password, path("root_ca"), cert, key)
