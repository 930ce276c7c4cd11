"""The real-time field as one site: the composition root of ``fleetlink field``.

``FieldSite(scenario, plan, clock, ...).start()`` starts, in order:

1. the links' infrastructure. The demo: ground truth on Zenoh at ``truth_listen`` (a peer others
   may connect to), an MQTT broker (``mqtt_url``, else one from ``brokers.start_demo_broker``),
   and a free loopback Zenoh endpoint where the agents meet the operator's peer. A secured site
   (``security=Security(...)``): deploy/'s broker and router with a password per party, the ACLs
   from ``shared/access.py`` and TLS (``site.security``, a ``SiteSecurity``); ground truth goes
   to the router as ``sim``.
2. the field (``field.realtime.RealtimeField``): every robot's board and lidar served like hardware.
3. with ``agents``: the UWB gateway (the scenario's anchors, fed in-process from the field's truth,
   fixes on MQTT; ``uwb-gateway`` on a secured site), the operator's link (``operator``: started,
   ``site.take_link()`` hands it over) and an agent per robot (``site.agents``, logged in as
   its robot on a secured site). Without agents: a board link per robot driven open-loop
   (``site.boards``), what ``fleetlink field --console off`` shows. When the plan has access
   points or dead zones, the field's radio (``site.radio``, field/radio.py) follows every robot's
   true pose and its agent's links pass nothing while out of reach (docs/field-scenarios.md).
   A scenario's ``agent_restart`` restarts that robot's agent (``FieldAgents.restart``); its other
   operator commands and link changes are refused when the site is made (the console is the
   operator here).

``stop()`` stops whatever started, in reverse. ``operator_link(operator)`` gives a further console
on a secured site its ``OperatorLink`` (not started).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import shutil
import sys
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetlink.field.radio import FleetRadio, RadioModel
from fleetlink.field.realtime import Endpoints, RealtimeField, TruthSample
from fleetlink.field.scenario import AgentRestart
from fleetlink.shared.access import GATEWAY_USER, SIM_USER
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import LinkName
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.worker import Worker
from fleetlink.site.brokers import AmqttBroker, MosquittoBroker, free_port, start_demo_broker
from fleetlink.site.operator import open_operator_link
from fleetlink.site.security import SiteSecurity

if TYPE_CHECKING:
    from fleetlink.agent.board.session import BoardSession
    from fleetlink.agent.config import Rates
    from fleetlink.field.open_loop import Motion
    from fleetlink.field.plans import FloorPlan
    from fleetlink.field.scenario import Event, Scenario
    from fleetlink.operator.links import OperatorLink
    from fleetlink.positioning.publisher import UwbGateway
    from fleetlink.site.agents import FieldAgents

log = logging.getLogger(__name__)

__all__ = ["FieldSite", "OpenLoopBoards", "Security", "uwb_gateway"]

NO_BROKER_URL = "mqtt://127.0.0.1:1"  # nothing listens: the MQTT fallback stays down


@dataclass(frozen=True)
class Security:
    """A secured site: deploy/'s broker and router, a login and ACL per party, TLS.

    ``operators``: the accounts (``op-<name>``), the first is the field's console; ``tls``: None
    means when openssl is installed.
    """

    operators: tuple[str, ...] = ("op-operator-1",)
    tls: bool | None = None


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr)


class FieldSite:
    def __init__(
        self,
        scenario: Scenario,
        plan: FloorPlan | None = None,
        clock: Clock | None = None,
        *,
        pty: bool = False,
        agents: bool = True,
        operator: str | None = None,
        mqtt_url: str | None = None,
        truth_listen: str | None = None,
        security: Security | None = None,
        rates: Rates | None = None,
        say: Callable[[str], None] = _to_stderr,
    ) -> None:
        if security is not None and mqtt_url is not None:
            raise ValueError("a secured site runs its own broker (deploy/'s configuration): no mqtt_url")
        if security is not None and operator is not None and operator not in security.operators:
            raise ValueError(f"the operator {operator!r} has no account on this site ({', '.join(security.operators)})")
        self.clock = clock or SystemClock()
        # The console is this run's operator: of the events a field hands over, an agent's restart
        # is the one the site carries out (with agents), the rest refused when the field is made.
        self.field = RealtimeField(
            scenario,
            plan,
            self.clock,
            truth_sink=self._truth_sample,
            pty=pty,
            on_command=self._command,
            carries_out=lambda ev: agents and isinstance(ev, AgentRestart),
        )
        self.scenario, self.plan = self.field.scenario, self.field.plan
        self.with_agents = agents
        self.operator = operator
        self.mqtt_url = mqtt_url
        self.truth_listen = truth_listen
        self.security_options = security
        self.rates = rates
        self.say = say
        self.security: SiteSecurity | None = None
        self.broker: MosquittoBroker | AmqttBroker | None = None
        self.mqtt_ok = True
        self.zenoh_endpoint: str | None = None  # where agents and operators meet on Zenoh
        self.endpoints: dict[str, Endpoints] = {}
        self.truth: Any = None  # TruthPublisher: a listening peer (demo), user sim of the router (secured)
        self.gateway: UwbGateway | None = None
        self.agents: FieldAgents | None = None
        self.boards: OpenLoopBoards | None = None
        self.link: OperatorLink | None = None
        self.radio: FleetRadio | None = None  # with agents, on a plan with a radio model
        self._hub: Any = None  # the demo's Zenoh meeting point when no operator link listens there
        self._hub_taken = False  # the demo's endpoint has its listener (the console's peer, or _hub)
        self._folder: Path | None = None
        self._truth_sinks: list[Callable[[TruthSample], None]] = []
        # Agents restarting (scenario events), each on a thread of its own; a restart due before the
        # agents have started waits for them (``_deferred``), and none starts once the site stops.
        self._restarts: list[Worker] = []
        self._deferred: list[str] = []
        self._restart_lock = threading.Lock()
        self._agents_up = False
        self._closing = False

    # -- life cycle -------------------------------------------------------------------------------

    def start(self) -> FieldSite:
        try:
            if self.security_options is not None:
                self._start_secured(self.security_options)
            else:
                self._start_demo()
            self.endpoints = self.field.start()
            if self.with_agents:
                self._start_agents()
            else:
                self.boards = OpenLoopBoards(self.field).start()
        except BaseException:
            self.stop()
            raise
        return self

    def _start_secured(self, options: Security) -> None:
        from fleetlink.field.truth import TruthPublisher

        robots = [r.name for r in self.scenario.robots]
        self.security = SiteSecurity(robots, options.operators, tls=options.tls).start()
        self.mqtt_url = self.security.mqtt_url
        self.zenoh_endpoint = self.security.zenoh_endpoint
        self.truth = TruthPublisher.open(self.clock, **self.security.zenoh_auth(SIM_USER))
        self._truth_sinks.append(self.truth.publish)

    def _start_demo(self) -> None:
        if self.truth_listen is not None:
            from fleetlink.field.truth import TruthPublisher

            try:
                self.truth = TruthPublisher.open(self.clock, listen=self.truth_listen)
                self._truth_sinks.append(self.truth.publish)
            except Exception as exc:  # zenoh raises its own ZError
                self.say(f"warning: cannot publish ground truth on {self.truth_listen}: {exc}; continuing without")
        if not self.with_agents:
            return
        if self.mqtt_url is None:
            self._folder = Path(tempfile.mkdtemp(prefix="fleetlink-site-"))
            self.broker, what = start_demo_broker(self._folder / "broker")
            if self.broker is None:
                self.say(
                    "warning: no MQTT broker: no mosquitto binary (.ci/install-mosquitto) and the amqtt "
                    "package did not start: running without the MQTT fallback and without UWB"
                )
                self.mqtt_url, self.mqtt_ok = NO_BROKER_URL, False
            else:
                self.mqtt_url = self.broker.url
                self.say(f"fleetlink field: MQTT on {self.mqtt_url} ({what})")
        self.zenoh_endpoint = f"tcp/127.0.0.1:{free_port()}"

    def _start_agents(self) -> None:
        from fleetlink.site.agents import FieldAgents

        assert self.mqtt_url is not None and self.zenoh_endpoint is not None
        if self.mqtt_ok:
            mqtt = (
                self.security.mqtt_settings(GATEWAY_USER)
                if self.security is not None
                else MqttSettings.from_url(self.mqtt_url)
            )
            self.gateway = uwb_gateway(self.scenario, self.plan, mqtt, self.clock)
            if self.gateway is not None:
                self.gateway.start()
                self._truth_sinks.append(self.gateway.on_truth_sample)
        if self.operator is not None:
            self.link = self.operator_link(self.operator).start()
        elif self.security is None:
            from fleetlink.links.zenoh import ZenohEndpoint

            self._hub = ZenohEndpoint(listen=[self.zenoh_endpoint], label="zenoh-hub")
            self._hub.start()
        s = self.security
        self.agents = FieldAgents(
            self.endpoints,
            clock=self.clock,
            zenoh_connect=[self.zenoh_endpoint],
            zenoh_mode="client" if s is not None else "peer",
            zenoh_passwords={r: s.passwords[r] for r in self.endpoints} if s is not None else None,
            zenoh_root_ca=s.ca_file if s is not None else None,
            mqtt_url=self.mqtt_url if s is None else None,
            mqtt=s.mqtt_settings() if s is not None else None,
            mqtt_passwords={r: s.passwords[r] for r in self.endpoints} if s is not None else None,
            operators=s.operators if s is not None else (),
            rates=self.rates,
            reachable=self._radio(),
        )
        self.agents.start()
        with self._restart_lock:
            self._agents_up = True
            for robot in self._deferred:
                self._restart(robot)
            self._deferred.clear()

    def stop(self) -> None:
        """Stop every part that started, the operator's link (unless taken) first, the brokers last."""
        link, self.link = self.link, None
        if link is not None:
            link.close()
        with self._restart_lock:
            self._closing = True  # no restart starts from now on
            restarts, self._restarts = self._restarts, []
        for restart in restarts:  # one under way finishes first: then every agent is stopped below
            restart.stop(30.0)
        if self.agents is not None:
            self.agents.stop()
            self.agents = None
        if self.boards is not None:
            self.boards.stop()
            self.boards = None
        if self.gateway is not None:
            self.gateway.stop()
            self.gateway = None
        self._truth_sinks.clear()
        if self.truth is not None:
            self.truth.close()
            self.truth = None
        self.field.stop()
        if self._hub is not None:
            with contextlib.suppress(Exception):
                self._hub.close()
            self._hub = None
        if self.broker is not None:
            self.broker.stop()
            self.broker = None
        if self.security is not None:
            self.security.stop()
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    def __enter__(self) -> FieldSite:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the operator's side ----------------------------------------------------------------------

    def operator_link(self, operator: str) -> OperatorLink:
        """An ``OperatorLink`` (not started) on this site as ``operator``: logged in on a secured
        site (any number of them, through its router). The demo has no router: the one operator
        link's Zenoh peer listens where the agents connect, so a second one would hear nothing."""
        if self.zenoh_endpoint is None or self.mqtt_url is None:
            raise RuntimeError("the site has no links: start it with agents first")
        if self.security is not None:
            auth = self.security.zenoh_auth(operator)
            connect = auth.pop("connect")
            return open_operator_link(
                self.clock,
                operator,
                mqtt_url=self.mqtt_url,
                mqtt=self.security.mqtt_settings(operator),
                zenoh_connect=connect,
                zenoh_auth=auth,
            )
        if self._hub_taken:
            raise RuntimeError("the demo field has one console (its Zenoh peer is the agents' meeting point)")
        self._hub_taken = True
        return open_operator_link(self.clock, operator, mqtt_url=self.mqtt_url, zenoh_listen=(self.zenoh_endpoint,))

    def take_link(self) -> OperatorLink:
        """The started operator's link; the caller closes it from now on."""
        if self.link is None:
            raise RuntimeError("no operator link: give FieldSite an operator")
        link, self.link = self.link, None
        return link

    def describe(self) -> list[str]:
        """How to join this site (a secured site's credentials), for the terminal."""
        return self.security.describe() if self.security is not None else []

    def _command(self, event: Event, t: float) -> None:
        """The field's handed-over events (on its physics thread): an agent's restart (the only kind
        the field lets through, ``carries_out``), carried out on a thread of its own so the physics
        goes on meanwhile, as a robot's hardware does while its agent process restarts."""
        if not isinstance(event, AgentRestart):  # not let through (``carries_out``); the physics goes on
            log.error("t=%.3f s: %s: nothing here carries it out", t, event.describe())
            return
        with self._restart_lock:
            if self._closing:
                log.info("t=%.3f s: %s: not carried out, the site is stopping", t, event.describe())
            elif not self._agents_up:
                log.info("t=%.3f s: %s: once the agents have started", t, event.describe())
                self._deferred.append(event.robot)
            else:
                self._restart(event.robot)

    def _restart(self, robot: str) -> None:
        """``robot``'s agent restarted on a thread of its own (under ``_restart_lock``)."""
        agents = self.agents
        assert agents is not None
        self._restarts = [w for w in self._restarts if w.running]  # those done need no joining
        self._restarts.append(
            Worker(f"restart-{robot}", clock=self.clock, target=lambda _w: agents.restart(robot)).start()
        )

    def _radio(self) -> Callable[[str, LinkName], bool] | None:
        """The radio's ``reachable(robot, link)``, kept up to date from the truth (None: the plan
        has no radio model: every link reaches everywhere)."""
        model = RadioModel.from_plan(self.plan)
        if not model.enabled:
            return None
        with self.field.lock:
            poses = {r.name: (r.board.state.x, r.board.state.y) for r in self.field.world.robots}
        radio = self.radio = FleetRadio(model, poses)

        def follow(sample: TruthSample) -> None:
            for link in radio.update(sample.robot, sample.x, sample.y):
                reach = "in reach" if radio.reachable(sample.robot, link) else "out of reach"
                log.info("%s: %s %s at (%.2f, %.2f)", sample.robot, link.value, reach, sample.x, sample.y)

        self._truth_sinks.append(follow)
        return radio.reachable

    def _truth_sample(self, sample: TruthSample) -> None:
        for sink in list(self._truth_sinks):
            sink(sample)


def uwb_gateway(scenario: Scenario, plan: FloorPlan, mqtt: MqttSettings, clock: Clock) -> UwbGateway | None:
    """The UWB simulator for the field: the scenario's anchors (else its plan's), a tag per robot;
    fed in-process from the field's truth, fixes out on MQTT. None with fewer than 3 anchors, or with
    the scenario's ``uwb`` off."""
    from fleetlink.positioning.anchors import Anchor
    from fleetlink.positioning.config import GatewayConfig
    from fleetlink.positioning.publisher import UwbGateway

    anchors = tuple(Anchor(*a) for a in scenario.uwb_anchors(plan.anchors))
    if len(anchors) < 3:
        return None
    config = GatewayConfig(anchors=anchors, auto_tags=True, walls=plan.segments(), mqtt=mqtt, gateway_id="field-uwb")
    return UwbGateway(config, clock, subscribe_truth=False)


class OpenLoopBoards:
    """Without agents: a board link per robot over the board's bytes, driven open-loop
    (field/open_loop.py: wander, a script, idle) from the simulated board's own sensors."""

    def __init__(self, field: RealtimeField) -> None:
        self.field = field
        self.sessions: list[tuple[str, BoardSession, Motion]] = []

    def start(self) -> OpenLoopBoards:
        from fleetlink.agent.board.session import BoardSession
        from fleetlink.devices.ports import SerialPort
        from fleetlink.field.open_loop import motion_for

        for i, spec in enumerate(self.field.scenario.robots):
            url = self.field.endpoints[spec.name].board
            session = BoardSession(functools.partial(SerialPort, url), self.field.clock, seed=i)
            session.start()
            self.sessions.append((spec.name, session, motion_for(spec, i)))
        return self

    def step(self, t: float) -> None:
        """Send each board the velocity its motion asks for at ``t`` (s since the start)."""
        boards = {r.name: r.board for r in self.field.world.robots}
        for name, session, motion in self.sessions:
            with self.field.lock:  # the physics thread steps the same boards
                v, w = motion(boards[name], t)
            session.set_velocity(v, w)

    def stop(self) -> None:
        for _, session, _ in self.sessions:
            session.set_velocity(0.0, 0.0)
        for _, session, _ in self.sessions:
            session.stop()
        self.sessions.clear()
