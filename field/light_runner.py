"""The light robots' shell: one worker publishes a whole ``LightFleet`` through the link layer.

``LightRunner(fleet, links, clock)``: on ``start`` it starts the links (idempotent), subscribes the
command keys of every robot (four wildcard subscriptions, ``fleetlink/v1/*/<topic>/*``, not four
per robot: the fleet drops what is not addressed to one of its robots), declares each robot's
liveliness token ``fleetlink/alive/v1/<robot>`` (``keys.alive_key``, as an agent does) on links
that hold tokens (``ZenohEndpoint``), and starts one ``Worker`` that sleeps until the fleet's next
deadline (at least ``TICK_S``), takes every message due and publishes it. Telemetry goes on the first link (the primary, Zenoh); a command is answered (its
ack, the lease) on the link it came on, from that link's delivery thread. One lock serialises the
core between the two threads; the core does the work, this file only moves bytes.

``open_light_fleet(n, clock, connect=..., listen=...)``: a runner over a Zenoh endpoint of its own
(``fleetlink field --light N``, bench/scale.py --light, tests).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from typing import Any

from fleetlink.field.light import COMMAND_TOPICS, LightFleet, LightSettings, light_names
from fleetlink.links.base import Link
from fleetlink.shared import keys
from fleetlink.shared.clock import Clock
from fleetlink.shared.worker import Worker

__all__ = ["LightRunner", "open_light_fleet"]

log = logging.getLogger(__name__)

MAX_SLEEP_S = 0.05
"""The worker never sleeps longer than this (a fleet with nothing due still checks for stop)."""
TICK_S = 0.005
"""Nor shorter: what fell due meanwhile goes out together. 500 robots at 20 Hz are a deadline every
0.1 ms; waking for each cost a core on its own. Each message keeps the time it was due, so the
batching shows (at most this much) as staleness at the console."""


class LightRunner(Worker):
    """``alive``: where each robot's liveliness token goes (default the contract's
    ``keys.alive_key``, as an agent's; None: no tokens); bench/zenoh_tokens.py puts them
    elsewhere to measure what the routers pay for them."""

    def __init__(
        self,
        fleet: LightFleet,
        links: Sequence[Link],
        clock: Clock,
        *,
        owns_links: bool = False,
        alive: Callable[[str], str] | None = keys.alive_key,
    ) -> None:
        if not links:
            raise ValueError("a light fleet needs at least one link")
        super().__init__("light-fleet", clock=clock)
        self.fleet = fleet
        self.links = tuple(links)
        self.lock = threading.Lock()
        self.published = 0
        self.unsent = 0
        self._owns = owns_links
        self._alive = alive

    def start(self) -> LightRunner:
        for link in self.links:
            for topic in COMMAND_TOPICS:
                link.subscribe(keys.sender_filter("*", topic), self._receiver(link))
            add_alive = getattr(link, "add_alive", None)
            if add_alive is not None and self._alive is not None:
                for name in self.fleet.robots:
                    add_alive(self._alive(name))
            link.start()
        super().start()
        return self

    def close(self) -> None:
        """Stop publishing; close the links if this runner opened them."""
        self.stop()
        if self._owns:
            for link in self.links:
                link.close()

    def _receiver(self, link: Link) -> Any:
        def receive(key: str, payload: bytes) -> None:
            with self.lock:
                answers = self.fleet.command(link.name, key, payload, self.clock.now(), self.clock.wall())
            self._publish(link, answers)

        return receive

    def _publish(self, link: Link, messages: list[tuple[str, bytes]]) -> None:
        for key, payload in messages:
            if link.publish(key, payload):
                self.published += 1
            else:
                self.unsent += 1

    def run(self) -> None:
        primary = self.links[0]
        while not self.stopping:
            with self.lock:
                out = self.fleet.due(self.clock.now(), self.clock.wall())
                nxt = self.fleet.next_deadline()
            self._publish(primary, out)
            self.wait(min(MAX_SLEEP_S, max(TICK_S, nxt - self.clock.now())))


def open_light_fleet(
    n: int,
    clock: Clock,
    *,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    settings: LightSettings | None = None,
    prefix: str = "L",
    alive: Callable[[str], str] | None = keys.alive_key,
    **auth: Any,
) -> LightRunner:
    """``n`` light robots (``L0000``...) on a Zenoh endpoint of their own (``ZenohEndpoint``'s
    keywords: a client of a router with ``connect`` and ``mode="client"``), started."""
    from fleetlink.links.zenoh import ZenohEndpoint

    names = light_names(n, prefix)
    link = ZenohEndpoint(listen=listen, connect=connect, clock=clock, label="zenoh-light", inbox_size=4096, **auth)
    link.start()  # first: the robots' deadlines start once the session is open (~0.5-1 s), not before
    try:
        fleet = LightFleet(names, clock.now(), settings)
        return LightRunner(fleet, [link], clock, owns_links=True, alive=alive).start()
    except BaseException:
        link.close()
        raise
