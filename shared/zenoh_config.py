"""Zenoh session configuration, built in one place so every process opens sessions the same way."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

__all__ = ["peer_config"]


def peer_config(
    listen: Sequence[str] = (), connect: Sequence[str] = (), *, mode: str = "peer", multicast_scouting: bool = False
) -> Any:
    """A ``zenoh.Config``: explicit endpoints, multicast scouting off unless asked for.

    With no ``listen`` endpoints the session listens nowhere (zenoh's default would be every
    interface). Sites link sessions by listing routers or peers explicitly (docs/operations.md).
    """
    import zenoh  # imported here so modules that only build configs stay importable without it

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf
