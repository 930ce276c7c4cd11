"""The live Foxglove server's shell (``fleetlink foxglove``): fleet links in, Foxglove's WebSocket
protocol out (docs/foxglove.md).

``FoxgloveLive`` listens to the fleet as the flight recorder does (the same endpoints,
``open_recorder_links``, subscribed to every fleetlink key; map and dose snapshots fetched with the
recorder's ``fetch_snapshots``) and serves what the pure core (site/foxglove_live.py) makes of it
with the ``foxglove-sdk`` package's WebSocket server. A link's thread only stamps the receive time
(the injected clock's ``wall()``) and queues the bytes; one worker turns them into records with
the core every ``TICK_S`` and logs them on the SDK's channels; a second worker fetches the
snapshots the core asks for. The SDK tells the core which channels the clients watch
(``ServerListener.on_subscribe``/``on_unsubscribe``), so nothing is built for a channel nobody
watches, and a client that subscribes to a grid gets its latest picture at once.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

from foxglove.websocket import ChannelView, Client, ServerListener

from fleetlink.links.base import Link
from fleetlink.shared import keys
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.worker import Worker
from fleetlink.site.foxglove_live import GRID_PERIOD_S, LiveCore
from fleetlink.site.foxglove_scene import Channel, Record
from fleetlink.site.recorder import fetch_snapshots

__all__ = ["DEFAULT_PORT", "FoxgloveLive"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's own default for a WebSocket connection (``ws://localhost:8765``)."""
TICK_S = 0.02
"""How often the worker takes what the links delivered (one wake per burst, not per message)."""
INBOX_SIZE = 50_000
"""Messages waiting for the worker; beyond it they are dropped and counted (the worker fell behind)."""
FETCH_PERIOD_S = 1.0


class FoxgloveLive:
    """Serves what ``links`` deliver over Foxglove's WebSocket protocol. ``start()``, then ``stop()``."""

    def __init__(
        self,
        links: Sequence[Link],
        clock: Clock | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        name: str = "fleetlink",
        grid_period_s: float = GRID_PERIOD_S,
        fetch: bool = True,
    ) -> None:
        """``port`` 0: any free port (``self.port`` says which once started)."""
        self.links = list(links)
        self.clock: Clock = clock or SystemClock()
        self.host = host
        self.name = name
        self.core = LiveCore(grid_period_s=grid_period_s)
        self.dropped = 0
        self._want_port = port
        self._lock = threading.Lock()
        self._inbox: deque[tuple[str, bytes, float]] = deque()
        self._inbox_lock = threading.Lock()
        self._channels: dict[str, Any] = {}
        self._context: Any = None
        self._server: Any = None
        self._to_fetch: set[tuple[str, str]] = set()
        self._fetch_lock = threading.Lock()
        self._working = Worker("foxglove-live", clock=self.clock, target=self._work_loop)
        self._fetching = Worker("foxglove-snapshots", clock=self.clock, target=self._fetch_loop) if fetch else None
        self._started = False

    @property
    def port(self) -> int:
        return int(self._server.port) if self._server is not None else self._want_port

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> FoxgloveLive:
        import foxglove

        self._context = foxglove.Context()
        self._server = foxglove.start_server(
            name=self.name,
            host=self.host,
            port=self._want_port,
            context=self._context,
            server_listener=_Listener(self),
        )
        for link in self.links:

            def receive(key: str, payload: bytes) -> None:
                self._put(key, payload, self.clock.wall())

            link.subscribe(keys.ZENOH_ALL, receive)
        self._working.start()
        if self._fetching is not None:
            self._fetching.start()
        for link in self.links:
            link.start()
        self._started = True
        return self

    def stop(self) -> None:
        """Close the links and the server. Idempotent."""
        if not self._started:
            return
        self._started = False
        for link in self.links:
            try:
                link.close()
            except Exception as exc:  # the server must stop whatever a transport does
                log.warning("closing %s: %s", link.name.value, exc)
        if self._fetching is not None:
            self._fetching.stop()
        self._working.stop()
        server, self._server = self._server, None
        if server is not None:
            server.stop()
        for channel in self._channels.values():
            channel.close()
        self._channels.clear()

    def __enter__(self) -> FoxgloveLive:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the links' side ------------------------------------------------------------------------

    def _put(self, key: str, payload: bytes, wall: float) -> None:
        with self._inbox_lock:
            if len(self._inbox) >= INBOX_SIZE:
                self.dropped += 1
                return
            self._inbox.append((key, payload, wall))

    # -- the worker -----------------------------------------------------------------------------

    def _work_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            worker.wait(TICK_S)
            try:
                self.step()
            except Exception:  # keep serving whatever one batch did
                log.exception("foxglove live: a batch failed")

    def step(self) -> int:
        """Take what the links delivered, send what is due. How many records were sent."""
        with self._inbox_lock:
            batch, self._inbox = self._inbox, deque()
        core = self.core
        with self._lock:
            records: list[Record] = []
            for key, payload, wall in batch:
                records += core.receive(key, payload, wall)
            records += core.due(self.clock.now(), self.clock.wall())
            announced, core.announced = core.announced, []
            reasons, core.new_reasons = core.new_reasons, []
            wanted = core.wanted()
        for reason in reasons:  # once per reason; the count goes on in core.rejected
            log.warning(
                "foxglove live: refused a message that is not wire-valid (%s); further ones are counted", reason
            )
        for channel in announced:
            self._advertise(channel)
        self._log(records)
        if wanted and self._fetching is not None:
            with self._fetch_lock:
                self._to_fetch.update(wanted)
            self._fetching.wake()
        return len(records)

    def _advertise(self, channel: Channel) -> Any:
        import foxglove

        found = self._channels.get(channel.topic)
        if found is None:
            schema = foxglove.Schema(name=channel.schema_name, encoding="jsonschema", data=channel.schema)
            found = self._channels[channel.topic] = foxglove.Channel(
                channel.topic, schema=schema, message_encoding="json", context=self._context
            )
        return found

    def _log(self, records: list[Record]) -> None:
        for r in records:
            self._advertise(r.channel).log(r.data, log_time=r.log_time_ns)

    # -- the clients' side (the SDK's threads) --------------------------------------------------

    def subscribed(self, topic: str) -> None:
        with self._lock:
            records = self.core.subscribe(topic, self.clock.now(), self.clock.wall())
        self._log(records)

    def unsubscribed(self, topic: str) -> None:
        with self._lock:
            self.core.unsubscribe(topic)

    # -- snapshots ------------------------------------------------------------------------------

    def _fetch_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            worker.wait(FETCH_PERIOD_S)
            with self._fetch_lock:
                wanted, self._to_fetch = sorted(self._to_fetch), set()
            fetch_snapshots(
                self.links, wanted, lambda _link, key, payload: self._put(key, payload, self.clock.wall()),
                lambda: worker.stopping,
            )  # fmt: skip


class _Listener(ServerListener):
    """The SDK's listener: which channels the clients watch."""

    def __init__(self, live: FoxgloveLive) -> None:
        self.live = live

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        try:
            self.live.subscribed(channel.topic)
        except Exception:  # an exception must not reach the SDK's thread
            log.exception("foxglove live: subscribing %s", channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        try:
            self.live.unsubscribed(channel.topic)
        except Exception:
            log.exception("foxglove live: unsubscribing %s", channel.topic)
