"""The agent process in real time: ``AgentNode`` (agent/node.py) in workers, on real ports and links.

``AgentNode`` is the whole agent as steps; this shell only gives it time and threads:

* the board session's poll worker (agent/board/session.py) over the serial port;
* the control worker: ``AgentNode.control(now)`` at ``control_hz`` while the robot drives, once
  per pose when it is idle, woken at once by a command that sets an idle robot moving (a UWB fix
  does not wake it);
* the links' own delivery threads (fleetlink.links: Zenoh's in-order delivery, paho's loop),
  which hand every payload to ``AgentNode.on_input``;
* with a ``lidar`` URL in robot.toml, the lidar worker (and, with loop closure on, the closure
  search worker, agent/mapping/worker.py ``SearchWorker``): ``LidarFeed.step(now)`` reads a quarter
  turn at a time into the node's map keeper (mapping, frame restarts, planner renewal:
  agent/mapping/keeper.py), serves the map on the Zenoh link (``fleetlink/v1/<robot>/map``,
  docs/mapping.md), and reports a failing lidar (``lidar_fault``/``lidar_ok`` events, an error in
  ``State.errors`` while it lasts) while driving goes on on the ultrasonic guard.

The lockstep site (fleetlink.site.lockstep) drives the same ``AgentNode`` without threads.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from fleetlink.agent.board.session import BoardSession
from fleetlink.agent.config import AgentConfig
from fleetlink.agent.core import AgentCore
from fleetlink.agent.links.mqtt_link import agent_mqtt_link
from fleetlink.agent.links.zenoh_link import agent_zenoh_link
from fleetlink.agent.mapping.keeper import MapKeeper
from fleetlink.agent.mapping.worker import SearchWorker
from fleetlink.agent.node import POLL_RATES, AgentNode, LidarFeed, mapper_config
from fleetlink.devices.ports import Port
from fleetlink.links.gated import GatedLink
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import LinkName
from fleetlink.shared.worker import Worker

log = logging.getLogger(__name__)

__all__ = ["POLL_RATES", "AgentRuntime"]


class AgentRuntime:
    """One robot's agent. ``start()`` / ``stop()``; safe to use as a context manager."""

    def __init__(
        self,
        config: AgentConfig,
        clock: Clock | None = None,
        *,
        open_port: Callable[[], Port] | None = None,
        seed: int | None = None,
        scan_sink: Callable[[Any], None] | None = None,
        reachable: Callable[[LinkName], bool] | None = None,
    ) -> None:
        """``reachable``: the simulated field's radio (site/agents.py): while it says False for a
        link, that link passes nothing either way and reads down (``links.gated.GatedLink``);
        ``zenoh`` and ``mqtt`` stay the endpoints themselves."""
        self.config = config
        self.clock = clock or SystemClock()
        robot = config.robot
        self.board = BoardSession(
            open_port or _serial_opener(config.board), self.clock, rates=POLL_RATES, seed=seed, direct=True
        )
        self.node = node = AgentNode(config, self.clock, self.board, scan_sink=scan_sink)
        self.zenoh: ZenohEndpoint | None = None
        self.mqtt: MqttEndpoint | None = None
        if config.zenoh is not None:
            self.zenoh = agent_zenoh_link(robot, config.zenoh)
            zenoh = _gated(self.zenoh, reachable)
            node.links.append(zenoh)
            node.map_link = zenoh
        if config.mqtt is not None:
            self.mqtt = agent_mqtt_link(robot, config.mqtt, node.connection_payload, seed=seed)
            node.links.append(_gated(self.mqtt, reachable))
        node.subscribe()
        self.links = node.links
        self._control = Worker(f"agent-{robot}", clock=self.clock, target=self._control_loop)
        node.on_started = self._control.wake
        self._lidar: Worker | None = None
        self._search: SearchWorker | None = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> AgentRuntime:
        self.board.start()
        for link in self.links:
            try:
                link.start()
            except Exception as exc:  # one link failing to open must not take the robot down
                log.error("%s link failed to start: %s", link.name.value, exc)
        self._control.start()
        if self.config.lidar:
            mapping = mapper_config(self.config)
            if mapping.closer is not None:  # loop closure's checks on a thread of their own
                self._search = SearchWorker(f"closure-{self.config.robot}", clock=self.clock).start()
            self.node.open_map(MapKeeper(mapping, search=self._search))
            # Mapping at a lower priority: on a host short of CPU, poses, commands and the board's
            # polls go first; a scan mapped late is only a map a little behind.
            self._lidar = Worker(
                f"lidar-{self.config.robot}", clock=self.clock, target=self._lidar_loop, background=True
            ).start()
        return self

    def stop(self) -> None:
        """The shutdown contract (Ctrl-C and SIGTERM alike, cli/main.py): no more control, the
        robot halted (zero velocity and the payload off, confirmed by the board), then the links
        closed (the retained ``Connection`` says OFFLINE), then the board session."""
        self._control.stop()
        if self._lidar is not None:
            self._lidar.stop()
            self._lidar = None
        if self._search is not None:
            self._search.stop()
            self._search = None
        if self.board.snapshot.connected:
            self.node.halt()
        self.node.close()
        for link in reversed(self.links):
            link.close()
        self.board.stop()

    def __enter__(self) -> AgentRuntime:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the workers ------------------------------------------------------------------------------

    def _control_loop(self, worker: Worker) -> None:
        node = self.node
        while not worker.stopping:
            next_t = node.control(self.clock.now())
            worker.wait(max(0.0, next_t - self.clock.now()))

    def _lidar_loop(self, worker: Worker) -> None:
        from fleetlink.agent.lidar.driver import LidarDriver

        url = str(self.config.lidar)
        feed = LidarFeed(self.node, lambda: LidarDriver.open(url, self.clock))
        try:
            while not worker.stopping:
                next_t = feed.step(self.clock.now())
                worker.wait(max(0.0, next_t - self.clock.now()))
        finally:
            feed.close()

    # -- what tests and tools read ----------------------------------------------------------------

    @property
    def core(self) -> AgentCore:
        return self.node.core

    @property
    def mapper(self) -> Any:
        keeper = self.node.keeper  # the runtime maps in line (AgentNode.open_map's default)
        return keeper.mapper if isinstance(keeper, MapKeeper) else None

    @property
    def lidar_fault(self) -> str | None:
        return self.node.lidar_fault

    @property
    def scans(self) -> int:
        return self.node.scans

    @property
    def published(self) -> int:
        return self.node.published

    @property
    def _lock(self) -> threading.Lock:
        return self.node._lock

    @property
    def _thread(self) -> threading.Thread | None:
        return self._control._thread

    @property
    def pans_topic(self) -> str:
        return self.node.pans_topic

    @property
    def key_prefix(self) -> str:
        return keys.key(self.config.robot, "state").rsplit("/", 1)[0]


def _gated(link: Any, reachable: Callable[[LinkName], bool] | None) -> Any:
    """The link itself, or behind the radio's gate for its name."""
    if reachable is None:
        return link
    name = link.name
    return GatedLink(link, lambda: reachable(name))


def _serial_opener(url: str) -> Callable[[], Port]:
    from fleetlink.devices.ports import SerialPort

    return lambda: SerialPort(url)
