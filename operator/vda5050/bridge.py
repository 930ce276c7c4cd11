"""The VDA 5050 bridge's thin shell: MQTT (one client per vehicle, for its own last will) and the
operator link (Zenoh primary, MQTT fallback) around the pure ``VehicleCore``.

A robot becomes a vehicle when its first fleetlink ``State`` arrives (or at start, for the robots
named). Its MQTT client (``links.mqtt.MqttEndpoint``) subscribes to the vehicle's ``order`` and
``instantActions``, has the last will ``CONNECTIONBROKEN`` and says ``ONLINE`` (retained, QoS 1)
on every (re)connect and ``OFFLINE`` on a clean close. A ``Worker`` ticks every vehicle's core
(periodic state, visualization, lease renewals). One lock serialises the cores.
"""

from __future__ import annotations

import functools
import logging
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

from fleetlink.links.mqtt import MqttEndpoint, MqttMessage
from fleetlink.operator.linkmanager import Failed, Switch
from fleetlink.operator.links import OperatorLink
from fleetlink.operator.vda5050.core import (
    Log,
    Out,
    Publish,
    SendActions,
    SendLease,
    SendOrder,
    VehicleConfig,
    VehicleCore,
)
from fleetlink.operator.vda5050.schema import SchemaValidator, load_schemas
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import InstantActions, LeaseRequest, Order, State
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.worker import Worker

__all__ = ["MAX_VEHICLES", "TICK_S", "Vda5050Bridge"]

log = logging.getLogger(__name__)

TICK_S = 0.1
MAX_VEHICLES = 512
"""Vehicles one bridge serves at most (each has a core and an MQTT client): a flood of ``State``
under ever new robot ids must not grow the bridge without bound. More are refused, counted
(``refused_vehicles``) and logged once."""


class _Vehicle:
    def __init__(self, core: VehicleCore, endpoint: MqttEndpoint) -> None:
        self.core = core
        self.endpoint = endpoint


class Vda5050Bridge:
    """Every fleetlink robot heard on ``link`` as a VDA 5050 vehicle on the broker ``mqtt``."""

    def __init__(
        self,
        clock: Clock,
        link: OperatorLink,
        mqtt: MqttSettings,
        *,
        manufacturer: str = "fleetlink",
        interface: str = "uagv",
        map_id: str = "site",
        robots: Sequence[str] = (),
        state_period_s: float = 5.0,
        visualization_period_s: float = 1.0,
        validator: SchemaValidator | None = None,
        max_vehicles: int = MAX_VEHICLES,
    ) -> None:
        self.clock = clock
        self.link = link
        self.mqtt = mqtt
        self.manufacturer = manufacturer
        self.interface = interface
        self.map_id = map_id
        self.robots = tuple(robots)
        self.state_period_s = state_period_s
        self.visualization_period_s = visualization_period_s
        self.validator = validator or SchemaValidator(load_schemas())
        self.vehicles: dict[str, _Vehicle] = {}
        self.max_vehicles = max_vehicles
        self.refused_vehicles = 0
        """Robots not made vehicles because ``max_vehicles`` were already served."""
        self._lock = threading.RLock()
        self._undelivered: deque[Failed] = deque(maxlen=4096)
        """Commands the operator link gave up on (its poll thread), for the tick to hand on."""
        self._closed = False
        self._ticker = Worker("vda5050-tick", clock=clock, target=self._tick_loop)

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> Vda5050Bridge:
        for robot in self.robots:
            self._vehicle(robot)
        self.link.add_sink(self._fleet)
        self.link.add_listener(self._link_event)
        self.link.start()
        self._ticker.start()
        return self

    def close(self) -> None:
        self._ticker.stop()
        with self._lock:
            self._closed = True
            vehicles = list(self.vehicles.values())
        for v in vehicles:
            v.endpoint.close()  # OFFLINE, then a clean disconnect (no last will)
        self.link.close()

    def __enter__(self) -> Vda5050Bridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- vehicles -------------------------------------------------------------------------------

    def _vehicle(self, robot: str) -> _Vehicle | None:
        with self._lock:
            v = self.vehicles.get(robot)
            if v is not None or self._closed or (self.robots and robot not in self.robots):
                return v
            if len(self.vehicles) >= self.max_vehicles:
                self.refused_vehicles += 1
                if self.refused_vehicles == 1:
                    log.warning(
                        "robot %r not served: the bridge already serves %d vehicles (max_vehicles); "
                        "further robots are counted, not logged",
                        robot[:64],
                        self.max_vehicles,
                    )
                return None
            config = VehicleConfig(
                robot=robot,
                serial=robot,
                manufacturer=self.manufacturer,
                interface=self.interface,
                map_id=self.map_id,
                state_period_s=self.state_period_s,
                visualization_period_s=self.visualization_period_s,
            )
            core = VehicleCore(config, self.validator, sender=self.link.sender)
            will = core.will(self.clock.wall())
            endpoint = MqttEndpoint(
                self.mqtt,
                client_id=f"{self.link.sender}-{robot}"[:64],
                will=MqttMessage(will.topic, will.payload, will.qos, will.retain),
                on_connect=functools.partial(self._connected, robot),
                on_close=functools.partial(self._offline, robot),
                clock=self.clock,
                label=f"mqtt-vda5050-{robot}",
            )
            v = _Vehicle(core, endpoint)
            self.vehicles[robot] = v
            for sub in ("order", "instantActions"):
                endpoint.subscribe(core.topic(sub), functools.partial(self._master, robot, sub))
        endpoint.start()
        return v

    def _connected(self, robot: str, _endpoint: object = None) -> None:
        with self._lock:
            v = self.vehicles[robot]
            wall = self.clock.wall()
            outs = v.core.connection("ONLINE", wall) + v.core.factsheet(wall)
            self._dispatch(robot, v, outs)

    def _offline(self, robot: str, _endpoint: object = None) -> None:
        with self._lock:
            v = self.vehicles[robot]
            self._dispatch(robot, v, v.core.connection("OFFLINE", self.clock.wall()))

    # -- inputs ---------------------------------------------------------------------------------

    def _master(self, robot: str, sub: str, _key: str, payload: bytes) -> None:
        with self._lock:
            v = self.vehicles.get(robot)
            if v is None:
                return
            try:
                outs = v.core.receive(sub, payload, self.clock.now(), self.clock.wall())
            except Exception:  # keep serving: a bug on one message must not end the vehicle
                log.exception("%s: handling %s failed", robot, sub)
                return
            self._dispatch(robot, v, outs)

    def _fleet(self, msg: wire.Message, link: str, now: float) -> None:
        robot = msg.header.robot
        v = self.vehicles.get(robot)
        if v is None:
            if not isinstance(msg, State):
                return
            v = self._vehicle(robot)
            if v is None:
                return
        with self._lock:
            try:
                outs = v.core.fleet(msg, self.clock.now(), self.clock.wall())
            except Exception:
                log.exception("%s: handling fleetlink %s failed", robot, type(msg).TOPIC)
                return
            self._dispatch(robot, v, outs)

    def _link_event(self, event: Switch | Failed) -> None:
        if isinstance(event, Failed):
            self._undelivered.append(event)

    def _tick_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            self._tick_once()
            worker.wait(TICK_S)

    def _tick_once(self) -> None:
        with self._lock:
            while self._undelivered:
                f = self._undelivered.popleft()
                fv = self.vehicles.get(f.robot)
                if fv is not None:
                    try:
                        outs = fv.core.undelivered(f.topic, f.header_id, f.reason, self.clock.now())
                    except Exception:
                        log.exception("%s: handling an undelivered %s failed", f.robot, f.topic)
                        continue
                    self._dispatch(f.robot, fv, outs)
            for robot, v in list(self.vehicles.items()):
                try:
                    self._dispatch(robot, v, v.core.tick(self.clock.now(), self.clock.wall()))
                except Exception:
                    log.exception("%s: tick failed", robot)

    # -- outputs --------------------------------------------------------------------------------

    def _dispatch(self, robot: str, v: _Vehicle, outs: list[Out]) -> None:
        for out in outs:
            try:
                self._dispatch_one(robot, v, out)
            except Exception:  # keep serving: one output that cannot go must not stop the rest
                log.exception("%s: sending %s failed", robot, type(out).__name__)

    def _dispatch_one(self, robot: str, v: _Vehicle, out: Out) -> None:
        if isinstance(out, Publish):
            v.endpoint.publish(out.topic, out.payload, qos=out.qos, retain=out.retain)
        elif isinstance(out, SendOrder):
            msg = self.link.send(Order, robot, **out.fields)
            v.core.sent(out.tag, Order.TOPIC, msg.header.headerId)
        elif isinstance(out, SendActions):
            msg = self.link.send(InstantActions, robot, actions=out.actions)
            v.core.sent(out.tag, InstantActions.TOPIC, msg.header.headerId)
        elif isinstance(out, SendLease):
            header = self.link.counter.header(LeaseRequest.TOPIC, robot=robot)
            request = LeaseRequest(header=header, duration_s=out.duration_s, release=out.release)
            self.link.publish(request, links=("zenoh", "mqtt"))
        elif isinstance(out, Log):
            getattr(log, out.level, log.warning)("%s", out.text)

    # -- views ----------------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """Per vehicle: messages refused and invalid ones not sent, skipped nodes, actions FAILED
        for the robot's silence, leases released again."""
        with self._lock:
            return {
                r: {
                    "refused": dict(v.core.refused),
                    "invalid_out": dict(v.core.invalid_out),
                    "skipped_nodes": v.core.skipped_nodes,
                    "dropped_orders": v.core.dropped_orders,
                    "timed_out_actions": v.core.timed_out_actions,
                    "lease_rereleases": v.core.lease_rereleases,
                }
                for r, v in self.vehicles.items()
            }
