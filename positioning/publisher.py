"""The UWB gateway process shell: Zenoh truth in, MQTT fixes out, on an injected clock.

``UwbGateway(config, clock)`` owns an ``MqttEndpoint`` (credentials, TLS, TCP_NODELAY and the
jittered reconnect backoff of fleetlink.links.mqtt; its retained ``online`` status re-published
on every connect, ``offline`` as the last will and on a clean stop), optionally a
``ZenohEndpoint`` subscribed to ``fleetlink/v1/sim/*/truth``, and one worker that ticks
``GatewayCore`` at the configured rate. ``start()``/``stop()`` (or ``with``) so the real-time
field can run it in-process; it can also be fed directly with ``on_truth_sample`` (any object
with robot, x, y, theta, v) instead of Zenoh.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from fleetlink.links.mqtt import MqttEndpoint, MqttMessage
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Truth
from fleetlink.shared.worker import Worker

from .config import GatewayConfig
from .gateway import GatewayCore

__all__ = ["UwbGateway"]

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 5.0


class UwbGateway:
    def __init__(
        self,
        config: GatewayConfig,
        clock: Clock,
        *,
        zenoh_session: Any = None,
        subscribe_truth: bool = True,
        client_id: str | None = None,
    ) -> None:
        """``zenoh_session``: take truth from this open session (its owner closes it) instead of
        opening one as the configuration says."""
        self.config = config
        self.clock = clock
        self.core = GatewayCore(config)
        self._lock = threading.Lock()  # core is touched by the truth receiver and the tick worker
        self._subscribe_truth = subscribe_truth
        self._zenoh_session = zenoh_session
        self._client_id = client_id or f"fleetlink-{config.gateway_id}"
        self.mqtt: MqttEndpoint | None = None
        self.zenoh: ZenohEndpoint | None = None
        self._ticker: Worker | None = None
        self._logged: set[str] = set()
        self.published = 0

    # ----------------------------------------------------------------------------------------------
    # life cycle

    def start(self) -> UwbGateway:
        if self._ticker is not None:
            return self
        s = self.config.mqtt
        self.mqtt = MqttEndpoint(
            s,
            client_id=self._client_id,
            will=self.core.status("offline", 0.0),
            on_connect=lambda ep: ep.send(self._status("online")),  # again after every reconnect
            on_close=lambda ep: ep.send(self._status("offline")),
            clock=self.clock,
            label=f"mqtt-{self.config.gateway_id}",
        )
        self.mqtt.start()
        if self._subscribe_truth:
            self._start_zenoh()
        self._ticker = Worker(f"uwb-{self.config.gateway_id}", clock=self.clock, target=self._run).start()
        log.info(
            "UWB gateway %s: %d anchors, %s, %.3g Hz, MQTT %s as %s",
            self.config.gateway_id,
            len(self.config.anchors),
            "tags " + ", ".join(f"{t.id}->{t.robot}" for t in self.config.tags) if self.config.tags else "auto tags",
            self.config.rate_hz,
            s.url,
            s.username or "anonymous",
        )
        return self

    def stop(self) -> None:
        """Idempotent: stop ticking, say ``offline`` (retained), close what we opened."""
        ticker, self._ticker = self._ticker, None
        if ticker is not None:
            ticker.stop()
        zenoh, self.zenoh = self.zenoh, None
        if zenoh is not None:
            zenoh.close()
        mqtt, self.mqtt = self.mqtt, None
        if mqtt is not None:
            mqtt.close()

    def __enter__(self) -> UwbGateway:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def up(self) -> bool:
        """Connected to the MQTT broker."""
        return self.mqtt is not None and self.mqtt.up

    @property
    def refused(self) -> int:
        """CONNACKs refusing our credentials."""
        return self.mqtt.refused if self.mqtt is not None else 0

    # ----------------------------------------------------------------------------------------------
    # MQTT

    def _status(self, state: str) -> MqttMessage:
        with self._lock:
            return self.core.status(state, self.clock.wall())

    def _publish(self, pubs: list[MqttMessage]) -> None:
        mqtt = self.mqtt
        if mqtt is None or not mqtt.up:
            return  # QoS 0 telemetry: a fix that cannot go out now is worthless later
        for p in pubs:
            if mqtt.send(p):
                self.published += 1

    # ----------------------------------------------------------------------------------------------
    # truth in

    def _start_zenoh(self) -> None:
        if self._zenoh_session is not None:
            z = ZenohEndpoint(session=self._zenoh_session, clock=self.clock, label="zenoh-uwb")
        else:
            a = self.config.zenoh_auth
            z = ZenohEndpoint(
                listen=self.config.zenoh_listen,
                connect=self.config.zenoh_connect,
                clock=self.clock,
                label="zenoh-uwb",
                mode=a.mode,
                username=a.username,
                password=a.password,
                root_ca=a.root_ca,
            )
        z.subscribe(keys.ZENOH_ALL_TRUTH, self._on_truth_bytes)
        z.start()
        self.zenoh = z

    def _on_truth_bytes(self, key: str, payload: bytes) -> None:
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            with self._lock:
                self.core.counts["truth_bad"] += 1
            self._once(f"bad truth on {key}: {exc.reason}")
            return
        if isinstance(msg, Truth):
            self.on_truth(msg.header.robot, msg.x, msg.y, msg.theta, msg.v)

    def on_truth(self, robot: str, x: float, y: float, theta: float = 0.0, v: float = 0.0) -> bool:
        with self._lock:
            return self.core.on_truth(robot, x, y, self.clock.now(), theta, v)

    def on_truth_sample(self, sample: Any) -> None:
        """For the field's ``truth_sink``: any object with robot, x, y (theta, v optional)."""
        self.on_truth(sample.robot, sample.x, sample.y, getattr(sample, "theta", 0.0), getattr(sample, "v", 0.0))

    def _once(self, reason: str) -> None:
        if reason not in self._logged:
            self._logged.add(reason)
            log.warning("%s (further ones counted only)", reason)

    # ----------------------------------------------------------------------------------------------
    # the ranging loop

    def _run(self, worker: Worker) -> None:
        period = 1.0 / self.config.rate_hz
        clock = self.clock
        next_tick = clock.now() + period
        next_status = clock.now() + STATUS_PERIOD_S
        while not worker.stopping:
            now = clock.now()
            if now < next_tick:
                worker.wait(next_tick - now)
                continue
            # Late (a stall): skip the missed rounds rather than burst them out.
            next_tick = max(next_tick + period, now)
            try:
                with self._lock:
                    pubs = self.core.tick(now, clock.wall())
                    if now >= next_status:
                        next_status = now + STATUS_PERIOD_S
                        pubs.append(self.core.status("online", clock.wall()))
                self._publish(pubs)
            except Exception:
                log.exception("UWB gateway tick failed")
