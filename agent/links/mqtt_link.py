"""The fallback link: one paho-mqtt 2.x client on its own loop thread, reconnecting by itself.

Thin: every message's topic and bytes go to ``on_input(LinkName.MQTT, topic, payload)``.
Commands (and ``connection``) travel at QoS 1, telemetry at QoS 0. ``connection`` is retained,
with the last will CONNECTIONBROKEN; ONLINE is re-published after every (re)connect, OFFLINE on a
clean stop. The client comes from ``shared.mqtt.connect_client`` (credentials, TLS, the last
will, TCP_NODELAY on every socket it opens: QoS 1 with Nagle against delayed ACKs costs ~40 ms
per message), as in every fleetlink process. The loop is ours rather than ``loop_start`` so that reconnects use jittered
exponential backoff (a fleet whose broker restarts must not reconnect in lockstep) and so that a
publish from the control thread is written at once instead of waiting for the loop to wake.
"""

from __future__ import annotations

import contextlib
import logging
import random
import threading
from collections.abc import Callable, Sequence
from typing import Any

from fleetlink.shared import keys
from fleetlink.shared.messages import ConnectionState, LinkName
from fleetlink.shared.mqtt import MqttSettings, MqttWill, connect_client

log = logging.getLogger(__name__)

__all__ = ["COMMAND_QOS_TOPICS", "MqttLink"]

COMMAND_QOS_TOPICS = frozenset({"order", "actions", "teleop", "connection", "ack", "lease", "lease/request"})
"""Published/subscribed at QoS 1; everything else QoS 0."""

OnInput = Callable[[LinkName, str, bytes], None]

LOOP_TIMEOUT_S = 0.25
"""The loop's idle wake-up: inbound bytes and every publish (paho pokes its socket pair) wake it
at once, so this only paces keepalives and noticing ``stop`` when nothing else happens."""


class MqttLink:
    name = LinkName.MQTT

    def __init__(
        self,
        robot: str,
        on_input: OnInput,
        settings: MqttSettings,
        connection_payload: Callable[[ConnectionState], bytes],
        *,
        inputs: Sequence[str] = ("order", "actions", "teleop"),
        extra_topics: Sequence[str] = (),
        client_id: str | None = None,
        seed: int | None = None,
    ) -> None:
        self.robot = keys.check_robot_id(robot)
        self.on_input = on_input
        self.settings = settings
        self.connection_payload = connection_payload
        self.subscriptions = [(keys.key(robot, t), 1 if t in COMMAND_QOS_TOPICS else 0) for t in inputs]
        self.subscriptions += [(t, 0) for t in extra_topics]
        self.client_id = settings.client_id or client_id or f"agent-{robot}"
        self.keepalive_s = settings.keepalive_s
        self.backoff_min_s = settings.reconnect_min_s
        self.backoff_max_s = settings.reconnect_max_s
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._client: Any = None
        self._connected = False
        self.connects = 0
        self.publish_errors = 0

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        will = MqttWill(keys.key(self.robot, "connection"), self.connection_payload(ConnectionState.CONNECTIONBROKEN))
        c = connect_client(self.settings, client_id=self.client_id, will=will, start=False, rng=self._rng)
        c.max_queued_messages_set(256)  # QoS 1 acks queued while down; telemetry is simply dropped
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_message = self._on_message
        self._client = c
        self._thread = threading.Thread(target=self._run, name=f"mqtt-{self.robot}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Say OFFLINE (retained), disconnect cleanly (no last will) and end the loop thread."""
        c = self._client
        if c is None:
            return
        if self._connected:
            try:
                info = c.publish(
                    keys.key(self.robot, "connection"),
                    self.connection_payload(ConnectionState.OFFLINE),
                    qos=1,
                    retain=True,
                )
                c.loop_write()
                info.wait_for_publish(timeout=0.0)
            except Exception:  # best effort on the way out
                pass
        self._stop.set()
        with contextlib.suppress(Exception):
            c.disconnect()  # queues DISCONNECT, which also wakes the loop out of its select
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        self._connected = False
        self._client = None

    @property
    def up(self) -> bool:
        return self._connected

    def publish(self, topic: str, payload: bytes) -> bool:
        c = self._client
        if c is None or not self._connected:
            return False
        qos = 1 if topic in COMMAND_QOS_TOPICS else 0
        try:
            info = c.publish(keys.key(self.robot, topic), payload, qos=qos)
        except Exception as exc:
            self.publish_errors += 1
            log.warning("mqtt publish on %s failed: %s", topic, exc)
            return False
        return bool(info.rc == 0)

    # -- the loop -------------------------------------------------------------------------------

    def _run(self) -> None:
        import paho.mqtt.client as mqtt

        c = self._client
        backoff = self.backoff_min_s
        first = True
        need_connect = True
        while not self._stop.is_set():
            if need_connect:
                try:
                    if first:
                        c.connect(self.settings.host, self.settings.port, keepalive=self.keepalive_s)
                        first = False
                    else:
                        c.reconnect()
                    backoff = self.backoff_min_s
                    need_connect = False
                except OSError as exc:
                    delay = backoff * (0.5 + self._rng.random())  # jitter: 0.5x-1.5x
                    backoff = min(self.backoff_max_s, backoff * 2)
                    if self.connects == 0 or backoff >= self.backoff_max_s:
                        log.info("mqtt %s:%d unreachable (%s); retrying in %.2f s", *self._addr(), exc, delay)
                    self._stop.wait(delay)
                    continue
            rc = c.loop(timeout=LOOP_TIMEOUT_S)
            if rc != mqtt.MQTT_ERR_SUCCESS and not self._stop.is_set():
                self._connected = False
                need_connect = True
                delay = backoff * (0.5 + self._rng.random())
                backoff = min(self.backoff_max_s, backoff * 2)
                self._stop.wait(delay)

    def _addr(self) -> tuple[str, int]:
        return self.settings.host, self.settings.port

    # -- paho callbacks (on the loop thread) ------------------------------------------------

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if reason_code.is_failure:
            log.warning("mqtt %s:%d refused the connection: %s", *self._addr(), reason_code)
            return
        self._connected = True
        self.connects += 1
        client.subscribe(self.subscriptions)
        client.publish(
            keys.key(self.robot, "connection"),
            self.connection_payload(ConnectionState.ONLINE),
            qos=1,
            retain=True,
        )
        log.info("mqtt link up (%s:%d, connect #%d)", *self._addr(), self.connects)

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason_code: Any, properties: Any) -> None:
        if self._connected:
            log.warning("mqtt link down (%s); reconnecting", reason_code)
        self._connected = False

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        try:
            self.on_input(self.name, msg.topic, bytes(msg.payload))
        except Exception:  # a handler bug must not kill the loop thread
            log.exception("mqtt input handler failed")
