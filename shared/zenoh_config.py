"""Zenoh login settings: what a ``[zenoh]`` table says about joining a (secured) site. Pure; the
table is read by ``shared/link_tables.py`` (``ZenohTable``, ``zenoh_auth``), sessions are opened
in fleetlink.links.zenoh (``peer_config``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["ZenohAuth"]


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
