"""The MQTT endpoint's read path (links/mqtt.py ``_buffered_client_class``): what one ``recv``
brought is kept and handed out as paho asks for it, and QoS 0 publications are parsed from it
without paho's own handling. It must deliver exactly what paho delivers, in the same order,
however the bytes are cut into reads: tested against a plain paho client on the same bytes, with
no broker (a socket that hands out the bytes in the pieces a test chooses).
"""

from __future__ import annotations

import itertools
import struct
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from paho.mqtt.enums import CallbackAPIVersion

from fleetlink.links.mqtt import _buffered_client_class


def _remaining(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n % 128, n // 128
        out.append(byte | (128 if n else 0))
        if not n:
            return bytes(out)


def publish(topic: str, payload: bytes, *, qos: int = 0, retain: bool = False, mid: int = 1) -> bytes:
    t = topic.encode()
    body = struct.pack("!H", len(t)) + t + (struct.pack("!H", mid) if qos else b"") + payload
    return bytes([0x30 | (qos << 1) | int(retain)]) + _remaining(len(body)) + body


PINGRESP = b"\xd0\x00"


class PieceSocket:
    """Hands out ``pieces`` one per ``recv`` (at most what was asked), then would block."""

    def __init__(self) -> None:
        self.pieces: list[bytes] = []
        self.recvs = 0

    def recv(self, n: int) -> bytes:
        if not self.pieces:
            raise BlockingIOError
        self.recvs += 1
        piece = self.pieces.pop(0)
        if len(piece) > n:
            piece, rest = piece[:n], piece[n:]
            self.pieces.insert(0, rest)
        return piece

    def send(self, data: bytes) -> int:
        return len(data)

    def pending(self) -> int:
        return 0

    def close(self) -> None:
        pass

    def fileno(self) -> int:
        return -1


def client(buffered: bool, heard: list[tuple[str, bytes]]) -> tuple[Any, PieceSocket]:
    """A client as ``MqttEndpoint`` makes it (paho's ``on_message`` and, buffered, ``_fl_publish``)
    whose deliveries go to ``heard``."""
    cls = _buffered_client_class() if buffered else mqtt.Client
    c = cls(CallbackAPIVersion.VERSION2, client_id="reader", protocol=mqtt.MQTTv311)
    c.on_message = lambda _c, _u, msg: heard.append((msg.topic, bytes(msg.payload)))
    if buffered:
        c._fl_publish = lambda topic, payload: heard.append((topic, payload))
    c.on_socket_register_write = lambda *_: None  # PUBACKs are queued, not written
    sock = PieceSocket()
    c._sock = sock
    c._state = mqtt._ConnectionState.MQTT_CS_CONNECTED
    return c, sock


def read(pieces: list[bytes], buffered: bool) -> tuple[list[tuple[str, bytes]], int]:
    """Feed ``pieces`` as the network would (each one after the last was taken) and run the loop
    as ``MqttEndpoint._run`` does: one read when the socket is readable, then what is buffered."""
    heard: list[tuple[str, bytes]] = []
    c, sock = client(buffered, heard)
    for piece in pieces:
        sock.pieces.append(piece)
        while sock.pieces:
            assert c.loop_read() == mqtt.MQTT_ERR_SUCCESS
            while buffered and c.buffered_bytes():
                assert c.loop_read() == mqtt.MQTT_ERR_SUCCESS
    assert not buffered or c.buffered_bytes() == 0
    return heard, sock.recvs


packets = st.lists(
    st.tuples(
        st.sampled_from(["qos0", "qos0", "qos0", "qos1", "ping"]),
        st.text(st.characters(codec="utf-8", exclude_characters="\x00"), min_size=1, max_size=30),
        st.binary(max_size=300) | st.binary(min_size=16_000, max_size=17_000),
        st.booleans(),
    ),
    min_size=1,
    max_size=30,
)


@pytest.mark.slow
@settings(max_examples=150, deadline=None)
@given(packets=packets, cuts=st.lists(st.integers(0, 200_000), max_size=40))
def test_the_buffered_reader_delivers_what_paho_delivers_however_the_bytes_are_cut(
    packets: list[tuple[str, str, bytes, bool]], cuts: list[int]
) -> None:
    stream = b"".join(
        PINGRESP if kind == "ping" else publish(topic, payload, qos=int(kind == "qos1"), retain=retain, mid=i + 1)
        for i, (kind, topic, payload, retain) in enumerate(packets)
    )
    at = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    pieces = [stream[a:b] for a, b in itertools.pairwise(at) if b > a]
    expected = [(topic, payload) for kind, topic, payload, _ in packets if kind != "ping"]
    assert read(pieces, buffered=False)[0] == expected
    assert read(pieces, buffered=True)[0] == expected


def test_a_burst_in_one_read_costs_one_recv_and_a_long_length_is_parsed() -> None:
    burst = [publish(f"fleetlink/v1/r{i}/pose", bytes([i]) * (1 + i * 97), retain=i % 5 == 0) for i in range(200)]
    heard, recvs = read([b"".join(burst)], buffered=True)
    assert heard == [(f"fleetlink/v1/r{i}/pose", bytes([i]) * (1 + i * 97)) for i in range(200)]
    assert recvs < 40  # 64 KiB a read, the burst is ~1.9 MB; paho alone: 3-4 a packet
    assert read([b"".join(burst)], buffered=False)[1] >= 3 * 200
    big = publish("fleetlink/v1/r1/map", b"m" * 2_000_000)  # a 4-byte remaining length
    assert read([big[:5], big[5:70_000], big[70_000:]], buffered=True)[0] == [("fleetlink/v1/r1/map", b"m" * 2_000_000)]


def test_a_paho_without_the_private_read_path_gets_its_own_reads(monkeypatch: Any) -> None:
    # The buffered reads use paho 2.0-2.x's private read path; a paho that lacks it must still
    # connect and deliver (paho's own reads), not fail on the first packet.
    import fleetlink.links.mqtt as flm

    monkeypatch.setattr(flm, "_BUFFERED", None)
    monkeypatch.delattr(mqtt.Client, "_sock_recv")  # as if a later paho had renamed it
    plain = flm._buffered_client_class()
    assert plain.__name__ == "PlainClient" and issubclass(plain, mqtt.Client)
    client = plain(CallbackAPIVersion.VERSION2)
    assert client.buffered_bytes() == 0
    assert plain._packet_read is mqtt.Client._packet_read  # paho's own
    monkeypatch.setattr(flm, "_BUFFERED", None)  # the next caller builds the real one again
