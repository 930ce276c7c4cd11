"""Zenoh peers on loopback for tests.

Multicast scouting is OFF, so tests never discover (or get discovered by) anything else on the
host's network; peers find each other only through explicit ``tcp/127.0.0.1:<port>`` endpoints.

Zenoh runs subscriber/queryable callbacks on non-daemon Python threads that only end when their
session is closed: every session opened here is closed at teardown, otherwise the process hangs.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Sequence

import pytest
import zenoh

from tests.harness.mosquitto import free_port


def loopback_endpoint(port: int | None = None) -> str:
    return f"tcp/127.0.0.1:{port if port is not None else free_port()}"


def zenoh_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    *,
    mode: str = "peer",
    multicast_scouting: bool = False,
    scouting_delay_ms: int | None = None,
) -> zenoh.Config:
    """A zenoh.Config with explicit endpoints and multicast scouting off by default.

    ``listen`` is always written, so an empty list means "no listener" rather than zenoh's default
    of listening on every interface.

    ``scouting_delay_ms`` (zenoh's ``scouting/delay``, default 500) bounds how long ``zenoh.open``
    waits for its connect endpoints; measured here it often takes the full 500 ms on loopback. 0
    makes open return at once, but then wait for the peers (see ``wait_meshed``) before closing:
    with zenoh 1.10, closing a session whose connection is still being set up sometimes stalls
    10 s and raises "close operation timed out".
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if scouting_delay_ms is not None:
        config.insert_json5("scouting/delay", json.dumps(scouting_delay_ms))
    return config


class ZenohPeers(list[zenoh.Session]):
    """The opened sessions (unpack as ``a, b = zenoh_peers(2)``) plus their listen endpoints."""

    def __init__(self, sessions: Sequence[zenoh.Session], endpoints: Sequence[str]) -> None:
        super().__init__(sessions)
        self.endpoints: list[str] = list(endpoints)


def _open_listening(connect: Sequence[str], attempts: int = 5) -> tuple[zenoh.Session, str]:
    """Open a peer listening on a fresh loopback port (retried if the port got taken meanwhile)."""
    last: Exception | None = None
    for _ in range(attempts):
        endpoint = loopback_endpoint()
        try:
            config = zenoh_config(listen=[endpoint], connect=connect, scouting_delay_ms=0)
            return zenoh.open(config), endpoint
        except zenoh.ZError as exc:
            last = exc
    raise RuntimeError(f"could not open a zenoh peer on a free loopback port: {last}")


def wait_meshed(sessions: Sequence[zenoh.Session], timeout: float = 10.0) -> None:
    """Wait until every session sees every other one as a connected peer."""
    if len(sessions) < 2:
        return
    want = {str(s.info.zid()) for s in sessions}
    deadline = time.monotonic() + timeout
    while True:
        missing = {
            str(s.info.zid()): want - {str(s.info.zid())} - {str(z) for z in s.info.peers_zid()} for s in sessions
        }
        if not any(missing.values()):
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"zenoh peers not meshed after {timeout:.1f}s; missing links: {missing}")
        time.sleep(0.01)


@pytest.fixture
def zenoh_peers() -> Iterator[Callable[..., ZenohPeers]]:
    """``zenoh_peers(n=2) -> ZenohPeers``: n loopback peers, peer i connecting to peers 0..i-1.

    Sessions open with ``scouting/delay`` 0 (fast) and the factory returns only once the peers
    are connected to each other (which also keeps ``close`` fast, see ``zenoh_config``); declarations (subscribers, queryables)
    still need a moment to propagate, so tests should retry until a condition holds. Every
    session is closed at teardown.
    """
    opened: list[zenoh.Session] = []

    def make(n: int = 2) -> ZenohPeers:
        if n < 1:
            raise ValueError("zenoh_peers needs n >= 1")
        sessions: list[zenoh.Session] = []
        endpoints: list[str] = []
        for _ in range(n):
            session, endpoint = _open_listening(connect=endpoints)
            opened.append(session)
            sessions.append(session)
            endpoints.append(endpoint)
        wait_meshed(sessions)
        return ZenohPeers(sessions, endpoints)

    try:
        yield make
    finally:
        errors: list[Exception] = []
        for session in reversed(opened):
            try:
                session.close()
            except zenoh.ZError as exc:  # keep closing the rest: an open one hangs the process
                errors.append(exc)
        if errors:
            raise RuntimeError(f"closing zenoh sessions failed: {errors}")
