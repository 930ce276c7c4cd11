"""shared/mqtt.py and the security options of shared/zenoh_config.py: parsing with clear errors, and a
client that really logs in, sets TCP_NODELAY and reconnects after a broker restart."""

from __future__ import annotations

import json
import random
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

from fleetlink.links.mqtt import connect_client, nodelay_enabled
from fleetlink.links.zenoh import peer_config
from fleetlink.shared.config import ConfigError
from fleetlink.shared.config import parse as parse_config
from fleetlink.shared.link_tables import MqttTable, mqtt_settings
from fleetlink.shared.mqtt import MqttSettings
from tests.harness import wait_until
from tests.harness.deploy import DeployBroker, mosquitto_passwd


def parse(text: str, base_dir: Path | None = None) -> MqttSettings:
    """A ``[mqtt]`` table as every configuration file reads it: the schema, then its files."""
    table = parse_config(tomllib.loads(text)["mqtt"], MqttTable, source="robot.toml", where="mqtt")
    return mqtt_settings(table, source="robot.toml", base_dir=base_dir)


def test_full_table(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("s3cret\n")
    for name in ("ca.crt", "me.crt", "me.key"):
        (tmp_path / name).write_text("x")
    s = parse(
        """
        [mqtt]
        url = "mqtts://broker.example:9883"
        username = "r1"
        password_file = "pw"
        ca_file = "ca.crt"
        cert_file = "me.crt"
        key_file = "me.key"
        client_id = "agent-r1"
        keepalive_s = 3
        reconnect_min_s = 0.2
        reconnect_max_s = 4
        """,
        base_dir=tmp_path,
    )
    assert (s.host, s.port, s.tls, s.username, s.password) == ("broker.example", 9883, True, "r1", "s3cret")
    assert s.ca_file == str(tmp_path / "ca.crt") and s.key_file == str(tmp_path / "me.key")
    assert (s.client_id, s.keepalive_s, s.reconnect_min_s, s.reconnect_max_s) == ("agent-r1", 3, 0.2, 4.0)
    assert "s3cret" not in repr(s)
    assert s.url == "mqtts://broker.example:9883"


@pytest.mark.parametrize(
    ("url", "host", "port", "tls"),
    [
        ("mqtt://h", "h", 1883, False),
        ("mqtts://h", "h", 8883, True),
        ("mqtt://127.0.0.1:1884", "127.0.0.1", 1884, False),
    ],
)
def test_default_ports(url: str, host: str, port: int, tls: bool) -> None:
    s = MqttSettings.from_url(url)
    assert (s.host, s.port, s.tls) == (host, port, tls)


@pytest.mark.parametrize(
    ("body", "problem"),
    [
        ('url = "http://h"', "mqtt.url: invalid url 'http://h': scheme must be mqtt:// or mqtts://"),
        ('url = "mqtt://"', "no host"),
        ('url = "mqtt://u:p@h"', "put credentials in username/password_file"),
        ('url = "mqtt://h:99999"', "invalid url"),
        ('url = "mqtt://h/x"', "nothing after"),
        ('url = "mqtt://h"\nbogus = 1', "mqtt.bogus: unknown key; allowed: ca_file"),
        ('username = "r1"', "mqtt.url: missing required key"),
        ('url = "mqtt://h"\npassword = "p"', "a password needs a username"),
        ('url = "mqtt://h"\nusername = "r1"\npassword = "p"\npassword_file = "pw"', "not both"),
        ('url = "mqtt://h"\npassword_file = "nope"', "mqtt.password_file: no such file"),
        ('url = "mqtt://h"\nusername = "r1"\npassword_file = "empty"', "is empty"),
        ('url = "mqtt://h"\nca_file = "pw"', "need an mqtts:// url"),
        ('url = "mqtts://h"\ncert_file = "pw"', "both or neither"),
        ('url = "mqtt://h"\nkeepalive_s = 0', "mqtt.keepalive_s: must be >= 1, got 0"),
        ('url = "mqtt://h"\nreconnect_min_s = 5\nreconnect_max_s = 1', "must be >= reconnect_min_s"),
        ('url = "mqtt://h"\nusername = 3', "mqtt.username: expected a string, got int 3"),
    ],
)
def test_errors_name_the_key(tmp_path: Path, body: str, problem: str) -> None:
    (tmp_path / "pw").write_text("pw")
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ConfigError) as err:
        parse(f"[mqtt]\n{body}\n", base_dir=tmp_path)
    assert str(err.value).startswith("robot.toml: mqtt")
    assert problem in str(err.value)


@dataclass(frozen=True)
class _File:
    mqtt: MqttTable | None = None


def test_not_a_table() -> None:
    with pytest.raises(ConfigError, match="expected a table"):
        parse_config({"mqtt": "mqtt://h"}, _File, source="robot.toml")


def test_client_logs_in_sets_nodelay_and_reconnects(tmp_path: Path) -> None:
    passwd = mosquitto_passwd(tmp_path / "passwd", {"r1": "pw-r1"})
    broker = DeployBroker(tmp_path / "broker", "mosquitto.conf", passwd=passwd)
    broker.start()
    settings = MqttSettings(
        host=broker.host, port=broker.port, username="r1", password="pw-r1", reconnect_min_s=0.1, reconnect_max_s=0.5
    )
    client = connect_client(settings, client_id="agent-r1", rng=random.Random(1))
    connects: list[str] = []
    client.on_connect = lambda _c, _u, _f, reason, _p: connects.append(str(reason))
    try:
        wait_until(client.is_connected)
        assert nodelay_enabled(client)
        broker.kill()
        wait_until(lambda: not client.is_connected())
        broker.start()
        wait_until(lambda: client.is_connected() and "Success" in connects, timeout=20)
        assert nodelay_enabled(client)  # the new socket has it too
    finally:
        client.disconnect()
        client.loop_stop()
        broker.stop()


def test_backoff_is_jittered_per_client() -> None:
    settings = MqttSettings(host="127.0.0.1", port=1, reconnect_min_s=1.0, reconnect_max_s=8.0)
    bounds = set()
    for seed in range(5):
        c = connect_client(settings, start=False, rng=random.Random(seed))
        lo, hi = c._reconnect_min_delay, c._reconnect_max_delay
        assert 1.0 <= lo <= 2.0 and 4.0 <= hi <= 8.0 and lo <= hi
        bounds.add((lo, hi))
    assert len(bounds) == 5


def test_zenoh_client_security_options() -> None:
    conf = peer_config(connect=["tls/router:7447"], mode="client", username="r1", password="pw", root_ca="/ca.crt")
    assert json.loads(conf.get_json("transport/auth/usrpwd")) == {
        "user": "r1",
        "password": "pw",
        "dictionary_file": None,
    }
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == "/ca.crt"
    plain = peer_config(connect=["tcp/127.0.0.1:7447"])
    assert json.loads(plain.get_json("transport/auth/usrpwd/user")) is None
    with pytest.raises(ValueError, match="both or neither"):
        peer_config(username="r1")
    with pytest.raises(ValueError, match="both or neither"):
        peer_config(tls_cert="/c.crt")
