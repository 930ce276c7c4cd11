"""The UWB gateway end to end: truth on real Zenoh peers in, fixes out through a real Mosquitto."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import paho.mqtt.client as mqtt

from fleetlink.field.realtime import TruthSample
from fleetlink.field.scenario import site_geometry
from fleetlink.field.truth import TruthPublisher
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.positioning.config import MqttSettings, parse_config
from fleetlink.positioning.publisher import UwbGateway
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import FixStatus, UwbFix, UwbRanges

RATE_HZ = 10.0
WINDOW_S = 2.0


class Listener:
    """A plain paho subscriber recording (topic, payload, retain) per message."""

    def __init__(self, port: int, topics: list[str]) -> None:
        self.messages: list[tuple[str, bytes, bool]] = []
        self.lock = threading.Lock()
        self.ready = threading.Event()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"listener-{id(self)}")

        def on_connect(client: Any, userdata: Any, flags: Any, reason: Any, props: Any) -> None:
            client.subscribe([(t, 0) for t in topics])

        def on_subscribe(*args: Any) -> None:
            self.ready.set()

        def on_message(client: Any, userdata: Any, msg: Any) -> None:
            with self.lock:
                self.messages.append((msg.topic, bytes(msg.payload), bool(msg.retain)))

        self.client.on_connect = on_connect
        self.client.on_subscribe = on_subscribe
        self.client.on_message = on_message
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        assert self.ready.wait(5.0), "listener did not subscribe"

    def on(self, prefix: str) -> list[tuple[str, bytes, bool]]:
        with self.lock:
            return [m for m in self.messages if m[0].startswith(prefix)]

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def wait_for(cond: Callable[[], bool], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_fixes_and_pans_over_real_mosquitto_from_zenoh_truth(mosquitto, zenoh_peers) -> None:
    field_session, gw_session = zenoh_peers(2)
    config = parse_config(
        {
            "plan": "office",
            "gateway": {"id": "gw-test", "rate_hz": RATE_HZ},
            "tags": [{"id": "0d7f", "robot": "r1", "z": 0.3}],
            "noise": {"profile": "los"},
        },
        site=site_geometry,
    )
    config = replace(config, mqtt=MqttSettings("127.0.0.1", mosquitto.port, keepalive_s=2))
    listener = Listener(mosquitto.port, ["fleetlink/v1/+/uwb", "dwm/node/+/uplink/location", "fleetlink/uwb/#"])
    clock = SystemClock()
    truth = TruthPublisher(ZenohEndpoint(session=field_session), clock)
    stop = threading.Event()

    def field() -> None:  # r1 stands in the corridor; 20 Hz truth like the real field
        while not stop.is_set():
            truth.publish(TruthSample("r1", 0.0, 14.0, 9.75, 0.0, 0.0, 0.0, False))
            time.sleep(0.05)

    feeder = threading.Thread(target=field)
    feeder.start()
    gw = UwbGateway(config, clock, zenoh_session=gw_session)
    try:
        gw.start()
        assert wait_for(lambda: len(listener.on("fleetlink/v1/r1/uwb")) >= 2), "no fixes arrived"
        # Garbage on the truth key: counted, the gateway keeps serving.
        field_session.put(keys.truth_key("r1"), b"\xc1 not msgpack")
        assert wait_for(lambda: gw.core.counts["truth_bad"] == 1)
        # The configured rate, loosely (no tight timing asserts): a window's worth of fixes, timed.
        before = len(listener.on("fleetlink/v1/r1/uwb"))
        t0 = time.monotonic()
        want = round(RATE_HZ * WINDOW_S)
        wait_for(lambda: len(listener.on("fleetlink/v1/r1/uwb")) >= before + want, timeout=10 * WINDOW_S)
        n = len(listener.on("fleetlink/v1/r1/uwb")) - before
        expected = RATE_HZ * (time.monotonic() - t0)
        assert 0.5 * expected <= n <= 1.5 * expected, f"{n} fixes in a window expecting ~{expected:.0f}"

        fixes = [wire.decode_key(t, p) for t, p, _ in listener.on("fleetlink/v1/r1/uwb")]
        assert all(isinstance(f, UwbFix) for f in fixes)
        assert [f.header.headerId for f in fixes] == list(
            range(fixes[0].header.headerId, fixes[0].header.headerId + len(fixes))
        )
        for f in fixes:
            assert f.header.robot == "r1" and f.header.sender == "gw-test" and f.tag == "0d7f"
            assert f.status is FixStatus.OK and math.hypot(f.x - 14.0, f.y - 9.75) < 0.5
            assert f.measured_at <= f.header.timestamp and abs(f.measured_at - clock.wall()) < 60
        rmse = math.sqrt(sum((f.x - 14.0) ** 2 + (f.y - 9.75) ** 2 for f in fixes) / len(fixes))
        assert rmse < 0.2

        pans = listener.on("dwm/node/0d7f/uplink/location")
        assert len(pans) >= len(fixes) - 2
        doc = json.loads(pans[-1][1])
        assert list(doc) == ["position", "superFrameNumber", "timestamp"]
        assert set(doc["position"]) == {"x", "y", "z", "quality"} and 0 <= doc["position"]["quality"] <= 100
        assert isinstance(doc["timestamp"], str) and abs(int(doc["timestamp"]) / 1e6 - clock.wall()) < 60

        # Retained: a client arriving now gets the last location and the gateway's "online".
        late = Listener(mosquitto.port, ["dwm/node/+/uplink/location", "fleetlink/uwb/+/status"])
        try:
            assert wait_for(lambda: late.on("dwm/") and late.on("fleetlink/uwb/gw-test/status"))
            assert late.on("dwm/")[0][2] is True
            assert json.loads(late.on("fleetlink/uwb/gw-test/status")[0][1])["state"] == "online"
        finally:
            late.close()

        # Raw ranges travel too.
        ranges_listener = Listener(mosquitto.port, ["fleetlink/v1/r1/uwb/ranges"])
        try:
            assert wait_for(lambda: bool(ranges_listener.on("fleetlink/v1/r1/uwb/ranges")))
            t, p, _ = ranges_listener.on("fleetlink/v1/r1/uwb/ranges")[0]
            assert isinstance(wire.decode_key(t, p), UwbRanges)
        finally:
            ranges_listener.close()

        # The last will: the connection dies without a DISCONNECT -> the broker says "offline";
        # the gateway reconnects and says "online" again.
        gw.mqtt.client.socket().close()  # type: ignore[union-attr]
        status = "fleetlink/uwb/gw-test/status"

        def states() -> list[str]:
            return [json.loads(p)["state"] for _, p, _ in listener.on(status)]

        assert wait_for(lambda: "offline" in states()), states()
        assert wait_for(lambda: states()[-1] == "online" and states().count("online") >= 2, timeout=15), states()
    finally:
        stop.set()
        feeder.join()
        gw.stop()
        truth.close()
    assert wait_for(lambda: [json.loads(p)["state"] for _, p, _ in listener.on("fleetlink/uwb/")][-1] == "offline")
    listener.close()


def test_the_fleetlink_uwb_process(mosquitto, zenoh_peers, tmp_path) -> None:
    """The real command: its own Zenoh session (from the config) and MQTT client; SIGINT stops it
    and it says "offline"."""
    import signal
    import subprocess
    import sys

    peers = zenoh_peers(1)
    field_session = peers[0]
    cfg = tmp_path / "uwb.toml"
    cfg.write_text(
        f"""
plan = "office"
[gateway]
id = "gw-proc"
auto_tags = true
[mqtt]
url = "mqtt://127.0.0.1:{mosquitto.port}"
[zenoh]
connect = ["{peers.endpoints[0]}"]
"""
    )
    listener = Listener(mosquitto.port, ["fleetlink/v1/+/uwb", "fleetlink/uwb/#"])
    truth = TruthPublisher(ZenohEndpoint(session=field_session), SystemClock())
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetlink.cli.main", "uwb", "--config", str(cfg), "--seconds", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        ok = wait_for(
            lambda: (
                bool(truth.publish(TruthSample("scout-1", 0.0, 20.0, 5.0, 0.0, 0.0, 0.0, False)))
                or bool(listener.on("fleetlink/v1/scout-1/uwb"))
            ),
            timeout=20,
        )
        assert ok, "no fix from the fleetlink uwb process"
        fix = wire.decode_key(*listener.on("fleetlink/v1/scout-1/uwb")[-1][:2])
        assert isinstance(fix, UwbFix) and fix.tag == "scout-1" and fix.header.sender == "gw-proc"
    finally:
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=20)[0].decode()
        truth.close()
    assert proc.returncode in (0, 130), out
    assert "gateway gw-proc: 10 anchors" in out
    assert wait_for(lambda: json.loads(listener.on("fleetlink/uwb/gw-proc/status")[-1][1])["state"] == "offline")
    listener.close()
