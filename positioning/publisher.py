"""The UWB gateway process shell: Zenoh truth in, MQTT fixes out, on an injected clock.

``UwbGateway(config, clock)`` owns a paho client (TCP_NODELAY, retained ``online`` status
re-published on every connect, last will ``offline``), optionally a Zenoh session subscribed to
``fleetlink/v1/sim/*/truth``, and one thread that ticks ``GatewayCore`` at the configured rate.
``start()``/``stop()`` (or ``with``) so the real-time field can run it in-process; it can also be
fed directly with ``on_truth_sample`` (any object with robot, x, y, theta, v) instead of Zenoh.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import Any

from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import Truth

from .config import GatewayConfig
from .gateway import GatewayCore, Publication

__all__ = ["UwbGateway"]

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 5.0
MAX_WAIT_SLICE_S = 0.1  # the tick thread notices stop() within this


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
        self.config = config
        self.clock = clock
        self.core = GatewayCore(config)
        self._lock = threading.Lock()  # core is touched by the zenoh callback and the tick thread
        self._session = zenoh_session
        self._owns_session = False
        self._subscribe_truth = subscribe_truth
        self._subscriber: Any = None
        self._client_id = client_id or f"fleetlink-{config.gateway_id}"
        self._client: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.connected = threading.Event()
        self._logged: set[str] = set()
        self.published = 0
        self.refused = 0  # MQTT CONNACKs refusing our credentials

    # ----------------------------------------------------------------------------------------------
    # life cycle

    def start(self) -> UwbGateway:
        if self._thread is not None:
            return self
        self._stop.clear()
        self._start_mqtt()
        if self._subscribe_truth:
            self._start_zenoh()
        self._thread = threading.Thread(target=self._run, name=f"uwb-{self.config.gateway_id}", daemon=True)
        self._thread.start()
        log.info(
            "UWB gateway %s: %d anchors, %s, %.3g Hz, MQTT %s as %s",
            self.config.gateway_id,
            len(self.config.anchors),
            "tags " + ", ".join(f"{t.id}->{t.robot}" for t in self.config.tags) if self.config.tags else "auto tags",
            self.config.rate_hz,
            self.config.mqtt.url,
            self.config.mqtt.username or "anonymous",
        )
        return self

    def stop(self) -> None:
        """Idempotent: stop ticking, say ``offline`` (retained), close what we opened."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._subscriber is not None:
            try:
                self._subscriber.undeclare()
            except Exception:  # the session may already be closed by its owner
                log.debug("undeclare failed", exc_info=True)
            self._subscriber = None
        if self._owns_session and self._session is not None:
            self._session.close()
            self._session = None
            self._owns_session = False
        client, self._client = self._client, None
        if client is not None:
            if self.connected.is_set():
                with self._lock:
                    p = self.core.status("offline", self.clock.wall())
                info = client.publish(p.topic, p.payload, p.qos, p.retain)
                with contextlib.suppress(RuntimeError, ValueError):
                    info.wait_for_publish(timeout=2.0)
            client.disconnect()
            client.loop_stop()
            self.connected.clear()

    def __enter__(self) -> UwbGateway:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----------------------------------------------------------------------------------------------
    # MQTT

    def _start_mqtt(self) -> None:
        from fleetlink.shared.mqtt import MqttWill, connect_client

        s = self.config.mqtt
        w = self.core.status("offline", 0.0)
        # Credentials, TLS, TCP_NODELAY (Nagle costs ~40 ms per fix, GUIDE.md) and the jittered
        # reconnect backoff come from shared/mqtt.py, like every other fleetlink process.
        client = connect_client(
            s, client_id=self._client_id, will=MqttWill(w.topic, w.payload, w.qos, w.retain), start=False
        )

        def on_connect(client: Any, userdata: Any, flags: Any, reason: Any, props: Any) -> None:
            if getattr(reason, "is_failure", False):
                self.refused += 1
                self._once(f"MQTT connect to {s.url} as {s.username or 'anonymous'} refused: {reason}")
                return
            self.connected.set()
            with self._lock:
                p = self.core.status("online", self.clock.wall())
            client.publish(p.topic, p.payload, p.qos, p.retain)  # again after every reconnect

        def on_disconnect(client: Any, userdata: Any, flags: Any, reason: Any, props: Any) -> None:
            self.connected.clear()

        client.on_connect = on_connect
        client.on_disconnect = on_disconnect
        client.connect_async(s.host, s.port, keepalive=s.keepalive_s)
        client.loop_start()
        self._client = client

    def _publish(self, pubs: list[Publication]) -> None:
        client = self._client
        if client is None or not self.connected.is_set():
            return  # QoS 0 telemetry: a fix that cannot go out now is worthless later
        for p in pubs:
            client.publish(p.topic, p.payload, p.qos, p.retain)
            self.published += 1

    # ----------------------------------------------------------------------------------------------
    # truth in

    def _start_zenoh(self) -> None:
        if self._session is None:
            import zenoh

            from fleetlink.shared.zenoh_config import peer_config

            a = self.config.zenoh_auth
            self._session = zenoh.open(
                peer_config(
                    self.config.zenoh_listen,
                    self.config.zenoh_connect,
                    mode=a.mode,
                    username=a.username,
                    password=a.password,
                    root_ca=a.root_ca,
                )
            )
            self._owns_session = True
        self._subscriber = self._session.declare_subscriber(keys.ZENOH_ALL_TRUTH, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            msg = wire.decode_key(key, sample.payload.to_bytes())
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

    def _run(self) -> None:
        period = 1.0 / self.config.rate_hz
        clock = self.clock
        next_tick = clock.now() + period
        next_status = clock.now() + STATUS_PERIOD_S
        while not self._stop.is_set():
            now = clock.now()
            if now < next_tick:
                clock.sleep_until(min(next_tick, now + MAX_WAIT_SLICE_S))
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
