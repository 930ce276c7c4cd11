"""Zenoh session configuration, built in one place so every process opens sessions the same way."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import TomlReader

__all__ = ["ZenohAuth", "peer_config", "read_zenoh_auth"]


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


def peer_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    *,
    mode: str = "peer",
    multicast_scouting: bool = False,
    username: str | None = None,
    password: str | None = None,
    root_ca: str | None = None,
    tls_cert: str | None = None,
    tls_key: str | None = None,
) -> Any:
    """A ``zenoh.Config``: explicit endpoints, multicast scouting off unless asked for.

    With no ``listen`` endpoints the session listens nowhere (zenoh's default would be every
    interface). Sites link sessions by listing routers or peers explicitly (docs/operations.md).

    Security (a site router with deploy/zenohd.json5): ``username``/``password`` log in
    (``transport/auth/usrpwd``; the router's ACL knows agents by robot id, operators as
    ``op-<name>``); ``root_ca`` is the site CA that ``tls/<host>:<port>`` endpoints are verified
    against (the router's certificate must name ``<host>``); ``tls_cert``/``tls_key`` present a
    client certificate for mutual TLS.
    """
    import zenoh  # imported here so modules that only build configs stay importable without it

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if (username is None) != (password is None):
        raise ValueError("zenoh username and password go together (both or neither)")
    if username is not None:
        conf.insert_json5("transport/auth/usrpwd", json.dumps({"user": username, "password": password}))
    if (tls_cert is None) != (tls_key is None):
        raise ValueError("zenoh tls_cert and tls_key go together (both or neither)")
    tls = {"root_ca_certificate": root_ca, "connect_certificate": tls_cert, "connect_private_key": tls_key}
    for name, value in tls.items():
        if value is not None:
            conf.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
    return conf
