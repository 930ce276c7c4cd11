"""One robot agent per simulated robot, in-process, against the real-time field's boards over TCP.

Here, in the site, because an agent and the field meet only at the site: field/ never imports
agent/ (the agents talk to the field's boards and lidars through their bytes, like hardware).

``FieldAgents(field.endpoints, zenoh_connect=[...], mqtt_url=...)``: ``start()`` builds an
``AgentRuntime`` per robot (its own Zenoh session connecting to ``zenoh_connect``, the shared
broker for MQTT, which also carries the UWB fixes: tag id = robot name) and ``stop()`` stops
them all; ``restart(robot)`` stops one and starts it again (a scenario's ``agent_restart``). An
agent is the board's only master: do not also run a demo ``BoardSession`` on the same board.

Security (issue 8) can be switched on as on a real site: ``mqtt`` (a ``shared.mqtt.MqttSettings``,
instead of ``mqtt_url``: TLS, CA) with ``mqtt_passwords`` (robot -> password, username = robot id),
``zenoh_passwords`` likewise for a router's usrpwd (``zenoh_root_ca`` for tls/ endpoints), and
``operators``: the operator ids every agent accepts commands from (empty: anyone).

The field's radio (field/radio.py): ``reachable(robot, link)`` says whether a robot's link reaches
it now (``FieldSite`` gives one when its plan has access points or dead zones); each agent's
links then pass nothing while it says False (``AgentRuntime(reachable=...)``).

The disinfection robots (named ``uvc-*``) carry ``FIELD_LAMP`` (``field_uv``), so their agents keep
a UV dose layer, here and in lockstep runs (site/lockstep.py); they are round bases that may turn in
place beside furniture (``field_limits``). Each agent hears the other robots' poses and plans
around the ones standing still (``field_peers``, agent/peers.py).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import threading
from collections.abc import Callable, Mapping, Sequence

from fleetlink.agent.config import AgentConfig, Limits, MqttSettings, Rates, UvTable, ZenohSettings, mqtt_settings
from fleetlink.agent.runtime import AgentRuntime
from fleetlink.field.realtime import Endpoints
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import LinkName

log = logging.getLogger(__name__)

__all__ = ["FIELD_LAMP", "FIELD_PEERS_MAX", "FieldAgents", "field_limits", "field_peers", "field_uv"]

FIELD_LAMP = UvTable(uvc_power_w=40.0, height_m=0.6, dose_resolution_m=0.05)
"""The simulated disinfection robots' lamp: 40 W of UV-C (four 36 W low-pressure tubes, ~10 W of
UV-C each, derated) at 0.6 m, a point source; the default target (10 mJ/cm²) and 0.1 m dose cells
(docs/payload.md). With one tube a room's round takes four times as long (bench/coverage.py)."""


def field_uv(robot: str) -> UvTable | None:
    """The lamp of a simulated robot: the disinfection robots (``uvc-*``) have ``FIELD_LAMP``."""
    return FIELD_LAMP if robot.startswith("uvc-") else None


CREEP_SPEED_MPS = 0.05
"""How fast the field's domestic robots creep on inside the guard's stop distance (a robot vacuum's
pace at the wall: its bumper is the last stop)."""


def field_limits(robot: str) -> Limits:
    """The motion limits of a simulated robot: the disinfection robots (``uvc-*``) are round
    domestic bases, which may turn in place beside furniture; the scouts keep the seed's rule."""
    domestic = robot.startswith("uvc-")
    return Limits(round_base=domestic, creep_speed_mps=CREEP_SPEED_MPS if domestic else 0.0)


FIELD_PEERS_MAX = 8
"""Up to this many robots on the field, each agent hears every other's pose (``field_peers``). Each
pose is 20 Hz, so n robots cost n(n-1) x 20 decodes a second in all: a larger fleet (the scale
bench's 50) shares no poses, as a real site would name each robot's peers on its floor in
robot.toml."""


def field_peers(robot: str, robots: Sequence[str]) -> tuple[str, ...]:
    """The robots whose poses ``robot``'s agent hears to plan around: the field's other robots,
    when there are at most ``FIELD_PEERS_MAX`` of them in all."""
    return tuple(r for r in robots if r != robot) if len(robots) <= FIELD_PEERS_MAX else ()


class FieldAgents:
    def __init__(
        self,
        endpoints: Mapping[str, Endpoints],
        *,
        clock: Clock | None = None,
        zenoh_connect: Sequence[str] = (),
        zenoh_listen: Mapping[str, Sequence[str]] | None = None,
        zenoh_mode: str = "peer",
        zenoh_passwords: Mapping[str, str] | None = None,
        zenoh_root_ca: str | None = None,
        mqtt_url: str | None = None,
        mqtt: MqttSettings | None = None,
        mqtt_passwords: Mapping[str, str] | None = None,
        operators: Sequence[str] = (),
        map_id: str = "",
        rates: Rates | None = None,
        reachable: Callable[[str, LinkName], bool] | None = None,
    ) -> None:
        self.clock = clock or SystemClock()
        self.reachable = reachable
        base_mqtt = mqtt if mqtt is not None else (mqtt_settings(mqtt_url) if mqtt_url else None)
        self.configs: list[AgentConfig] = []
        for name, ep in endpoints.items():
            zpw = (zenoh_passwords or {}).get(name)
            m = base_mqtt
            if m is not None and mqtt_passwords is not None and name in mqtt_passwords:
                m = dataclasses.replace(m, username=name, password=mqtt_passwords[name], client_id=None)
            self.configs.append(
                AgentConfig(
                    robot=name,
                    board=ep.board,
                    lidar=ep.lidar,
                    tag=name,
                    map_id=map_id,
                    zenoh=ZenohSettings(
                        listen=tuple((zenoh_listen or {}).get(name, ())),
                        connect=tuple(zenoh_connect),
                        mode=zenoh_mode,
                        username=name if zpw is not None else None,
                        password=zpw,
                        root_ca=zenoh_root_ca,
                    ),
                    mqtt=m,
                    rates=rates or Rates(),
                    operators=tuple(operators),
                    uv=field_uv(name),
                    limits=field_limits(name),
                    peers=field_peers(name, list(endpoints)),
                )
            )
        self.agents: dict[str, AgentRuntime] = {}
        self._lock = threading.Lock()  # a restart (another thread) and stop() one at a time
        self._stopped = False

    def start(self) -> dict[str, AgentRuntime]:
        with self._lock:
            for i in range(len(self.configs)):
                self._start(i)
        return self.agents

    def _start(self, i: int) -> None:
        cfg = self.configs[i]
        radio = functools.partial(self.reachable, cfg.robot) if self.reachable is not None else None
        agent = AgentRuntime(cfg, self.clock, seed=i, reachable=radio)
        try:
            agent.start()
        except BaseException:
            agent.stop()  # what did start (its board session, links, workers) does not outlive it
            raise
        self.agents[cfg.robot] = agent

    def restart(self, robot: str) -> None:
        """``robot``'s agent stopped as its process is on a restart (the robot halted, its links'
        retained state OFFLINE) and a new one started from the same configuration: all the old one
        held in memory is gone, and its map begins again where the robot stands (in a new frame
        without UWB). A no-op once ``stop`` has begun; the same shutdown as the process's on SIGTERM
        (cli/main.py), then a new one, as ``systemctl restart`` does."""
        if self._stopped:
            return
        with self._lock:
            if self._stopped:
                return
            old = self.agents.pop(robot, None)
            if old is None:
                log.error("agent %s: no such agent to restart", robot)
                return
            log.warning("agent %s: restarting", robot)
            try:
                old.stop()
            except Exception:  # a new process starts whatever the old one left
                log.exception("stopping agent %s failed", robot)
            try:
                self._start(next(i for i, cfg in enumerate(self.configs) if cfg.robot == robot))
            except Exception:
                log.exception("agent %s did not start again: the robot has no agent", robot)

    def stop(self) -> None:
        self._stopped = True  # a restart waiting for the lock gives up
        with self._lock:
            for agent in self.agents.values():
                try:
                    agent.stop()
                except Exception:  # keep stopping the others
                    log.exception("stopping agent %s failed", agent.config.robot)
            self.agents.clear()

    def __enter__(self) -> FieldAgents:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
