"""The dose layer on the wire and over real Zenoh peers on loopback: ``DoseSnapshot``/``DoseUpdate``
round trips, bad input refused with ``WireError`` (cells of the wrong size, NaN, negative, oversized,
off the lattice, a patch outside the layer), a layer too large for one message cut *down*, the
agent's ``DoseShare`` answering queries and patching a copy, and ``fleetlink dose save`` writing the
report files from a robot's dose layer and map."""

from __future__ import annotations

import json
import math
import struct
import threading
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from fleetlink.agent.dose_layer import DoseKeeper, DosePublication, DoseSample
from fleetlink.agent.dose_share import DoseShare, fetch_dose
from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.agent.mapping.share import MapShare
from fleetlink.cli.main import main
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.dose import FloorMask, Lamp
from fleetlink.shared.dose_codec import (
    FULL_BITS,
    SharedDose,
    decode_cells,
    encode_cells,
    patch_fields,
    snapshot_fields,
    to_float32_down,
)
from fleetlink.shared.messages import MAX_DOSE_CELLS, MAX_DOSE_DATA, DoseEncoding, DoseSnapshot, DoseUpdate
from fleetlink.shared.wire import WireError
from tests.harness import wait_until

CLOCK = SimClock(start=100.0)
COUNTER = wire.HeaderCounter(CLOCK, robot="uvc-1", sender="agent-uvc-1")
COMMON = {"target_j_m2": 100.0, "lamp_on_s": 12.5, "unplaced_s": 1.5}
LAMP = Lamp(10.0, 0.6)


def _snapshot(
    dose: np.ndarray, res: float = 0.1, origin: tuple[float, float] = (-0.05, -0.05), **over: Any
) -> DoseSnapshot:
    fields = snapshot_fields(dose, res, origin, 3, **COMMON, lamp=LAMP)
    assert fields is not None
    return COUNTER.make(DoseSnapshot, **{**fields, **over})


def _layer(h: int = 30, w: int = 40, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.0, 250.0, size=(h, w))
    d[:5] = 0.0
    return d


def test_snapshot_round_trip_rounds_down_to_float32() -> None:
    dose = _layer()
    snap = _snapshot(dose)
    back = wire.decode(DoseSnapshot, wire.encode(snap))
    assert back == snap and back.encoding is DoseEncoding.ZLIB_F32LE and back.mantissa_bits == FULL_BITS
    assert wire.decode_key(keys.key("uvc-1", "dose"), wire.encode(snap)) == snap
    layer = SharedDose.from_snapshot(back)
    assert layer.cells.dtype == np.float32 and layer.cells.shape == dose.shape
    assert (layer.cells.astype(np.float64) <= dose).all()  # never more than counted
    assert np.allclose(layer.cells, dose, rtol=2**-23, atol=0)
    assert (layer.target_j_m2, layer.lamp_on_s, layer.unplaced_s) == (100.0, 12.5, 1.5)
    grid = layer.grid()
    assert grid.origin == pytest.approx((-0.05, -0.05)) and grid.lamp_seconds == 12.5


def test_a_value_float32_would_round_up_is_cut_down() -> None:
    x = 100.0 - 1e-7  # nearest float32 is 100.0: that would certify a cell short of the target
    assert float(np.float32(x)) == 100.0
    f = to_float32_down(np.array([[x, 100.0, 0.0]]))
    assert float(f[0, 0]) < 100.0 and float(f[0, 1]) == 100.0 and float(f[0, 2]) == 0.0


def test_update_round_trip_and_apply() -> None:
    dose = _layer()
    copy = SharedDose.from_snapshot(_snapshot(dose))
    newer = dose.copy()
    newer[10:14, 20:25] += 7.0
    f = patch_fields(newer, 0.1, (-0.05, -0.05), (10, 20, 14, 25), 4, 3, **COMMON)
    assert f is not None and (f["patch_width"], f["patch_height"]) == (5, 4)
    upd = wire.decode(DoseUpdate, wire.encode(COUNTER.make(DoseUpdate, **f)))
    assert copy.apply(upd) and copy.version == 4
    assert np.array_equal(copy.cells, to_float32_down(newer))
    assert not copy.apply(upd)  # stale: refused
    gap = wire.decode(DoseUpdate, wire.encode(COUNTER.make(DoseUpdate, **{**f, "version": 9, "base_version": 7})))
    assert not copy.apply(gap) and copy.version == 4  # a missed one: fetch a snapshot


def _bad_cells(data: bytes, width: int = 2, height: int = 2) -> str:
    with pytest.raises(WireError) as err:
        decode_cells(data, width, height)
    return err.value.reason


def test_bad_cells_are_refused_with_a_wire_error() -> None:
    four = struct.pack("<4f", 1.0, 2.0, 3.0, 4.0)
    assert decode_cells(zlib.compress(four), 2, 2).tolist() == [[1.0, 2.0], [3.0, 4.0]]
    assert _bad_cells(zlib.compress(four[:12])) == "cells: expected 16 bytes (2 x 2 float32), got 12"
    assert _bad_cells(zlib.compress(four + b"\0\0\0\0")) == "cells: expected 16 bytes (2 x 2 float32), got more"
    assert _bad_cells(zlib.compress(four)[:-4]).endswith("the zlib stream does not end there")
    assert _bad_cells(b"not zlib").startswith("cells: not valid zlib data")
    assert _bad_cells(zlib.compress(struct.pack("<4f", 1.0, math.nan, 3.0, 4.0))) == (
        "cells: not finite (NaN or infinity) in some cell"
    )
    assert _bad_cells(zlib.compress(struct.pack("<4f", 1.0, math.inf, 3.0, 4.0))).startswith("cells: not finite")
    assert _bad_cells(zlib.compress(struct.pack("<4f", 1.0, -2.0, 3.0, 4.0))).startswith("cells: doses must be 0-")
    assert _bad_cells(zlib.compress(struct.pack("<4f", 1.0, 2e9, 3.0, 4.0))).startswith("cells: doses must be 0-")
    # A layer claiming more cells than any layer may have is refused before anything is inflated.
    assert (
        _bad_cells(zlib.compress(b""), 65_535, 65_535)
        == f"cells: 65535 x 65535 cells is over the limit of {MAX_DOSE_CELLS}"
    )


def test_bad_messages_are_refused_with_a_wire_error() -> None:
    snap = _snapshot(_layer())
    raw = msgpack.unpackb(wire.encode(snap))

    def refused(**over: Any) -> str:
        with pytest.raises(WireError) as err:
            wire.decode(DoseSnapshot, msgpack.packb({**raw, **over}, use_bin_type=True))
        return err.value.reason

    assert refused(target_j_m2=math.nan) == "target_j_m2: non-finite number nan"
    assert refused(target_j_m2=0.0).startswith("target_j_m2: 0.0 out of range")
    assert refused(lamp_on_s=-1.0).startswith("lamp_on_s: -1.0 out of range")
    assert refused(mantissa_bits=24).startswith("mantissa_bits: 24 out of range")
    assert refused(encoding="zlib-f64").startswith("encoding:")
    assert refused(cells=bytes(MAX_DOSE_DATA + 1)).startswith("cells: ")  # oversized: refused unread
    # Decoded fine, but the cells are the wrong size for the layer: refused where they are inflated.
    wrong = wire.decode(DoseSnapshot, msgpack.packb({**raw, "width": 41}, use_bin_type=True))
    with pytest.raises(WireError, match=r"^cells: expected 4920 bytes \(41 x 30 float32\), got 4800$"):
        SharedDose.from_snapshot(wrong)
    off = wire.decode(DoseSnapshot, msgpack.packb({**raw, "origin_x": 0.03}, use_bin_type=True))
    with pytest.raises(WireError, match=r"^origin_x: 0.03 is not on the 0.1 m lattice"):
        SharedDose.from_snapshot(off)
    copy = SharedDose.from_snapshot(snap)
    f = patch_fields(_layer(), 0.1, (-0.05, -0.05), (0, 35, 2, 40), 4, 3, **COMMON)
    assert f is not None
    outside = COUNTER.make(DoseUpdate, **{**f, "col": 38})
    with pytest.raises(WireError, match="lies outside"):
        copy.apply(outside)
    nan_patch = COUNTER.make(DoseUpdate, **{**f, "cells": zlib.compress(struct.pack("<10f", *([math.nan] * 10)))})
    with pytest.raises(WireError, match="not finite"):
        copy.apply(nan_patch)
    assert copy.version == 3  # nothing changed by a refused patch


def test_a_layer_too_large_for_one_message_keeps_fewer_mantissa_bits() -> None:
    """400 x 400 distinct doses (640 KB as float32) fit only with the mantissa cut, always down."""
    dose = _layer(400, 400, seed=7)
    fields = snapshot_fields(dose, 0.1, (-0.05, -0.05), 1, **COMMON, lamp=LAMP)
    assert fields is not None
    bits = fields["mantissa_bits"]
    assert 0 < bits < FULL_BITS and len(fields["cells"]) <= MAX_DOSE_DATA
    raw = wire.encode(COUNTER.make(DoseSnapshot, **fields))
    assert len(raw) <= wire.MAX_PAYLOAD
    layer = SharedDose.from_snapshot(wire.decode(DoseSnapshot, raw))
    got = layer.cells.astype(np.float64)
    assert (got <= dose).all()
    lit = dose > 0
    assert ((dose[lit] - got[lit]) / dose[lit]).max() < 2.0**-bits
    assert layer.mantissa_bits == bits
    # The smallest layers keep every bit.
    assert snapshot_fields(dose[:10, :10], 0.1, (-0.05, -0.05), 1, **COMMON, lamp=LAMP)["mantissa_bits"] == FULL_BITS  # type: ignore[index]
    assert encode_cells(np.zeros((0, 0))) and decode_cells(encode_cells(np.zeros((0, 0))), 0, 0).shape == (0, 0)


# -- over real Zenoh ------------------------------------------------------------------------------

ROOM = np.full((60, 80), 100, dtype=np.int8)  # 4 m x 3 m at 0.05 m, walls all round, from (0, 0)
ROOM[1:-1, 1:-1] = 0


def _keeper_after(seconds: float, x: float = 2.0, y: float = 1.5) -> tuple[DoseKeeper, list[DosePublication]]:
    k = DoseKeeper(Lamp(10.0, 0.6), 100.0, 0.1, share_period=1.0)
    k.set_floor(FloorMask.from_occupancy(ROOM, 0.05, (0.0, 0.0)), 1)
    pubs = []
    n = round(seconds * 20)
    for i in range(n + 30):  # then 1.5 s off: the last publication goes out
        p = k.step(DoseSample(i / 20.0, x, y, i < n, True))
        if p is not None:
            pubs.append(p)
    return k, pubs


def test_share_serves_the_layer_and_patches_a_copy(zenoh_peers) -> None:  # type: ignore[no-untyped-def]
    peers = zenoh_peers(2)
    agent, other = (ZenohEndpoint(session=s) for s in peers)
    agent.start()
    other.start()
    got: list[bytes] = []
    lock = threading.Lock()

    def on_update(_key: str, payload: bytes) -> None:
        with lock:
            got.append(payload)

    other.subscribe(keys.key("uvc-1", DoseUpdate.TOPIC), on_update)
    keeper, pubs = _keeper_after(3.0)
    try:
        with DoseShare(agent, "uvc-1", SimClock()) as share:
            assert fetch_dose(other, "uvc-1", timeout=0.5) is None  # nothing published yet: no answer
            share.publish(pubs[0])
            snap: list[DoseSnapshot] = []

            def fetched() -> bool:
                s = fetch_dose(other, "uvc-1", timeout=1.0)
                if s is not None:
                    snap.append(s)
                return s is not None

            wait_until(fetched, timeout=10, message="the dose snapshot from the queryable")
            copy = SharedDose.from_snapshot(snap[0])
            assert copy.version == pubs[0].version
            for pub in pubs[1:]:
                share.publish(pub)
            wait_until(lambda: len(got) >= len(pubs) - 1, timeout=10, message="the patches")
            with lock:
                updates = [wire.decode_key(keys.key("uvc-1", DoseUpdate.TOPIC), p) for p in got]
            for upd in updates:
                assert copy.apply(upd)
            assert copy.version == keeper.version
            assert np.array_equal(copy.cells, to_float32_down(keeper.grid.dose))
            assert copy.lamp_on_s == pytest.approx(keeper.grid.lamp_seconds)
        assert fetch_dose(other, "uvc-1", timeout=0.5) is None  # stopped: silent
    finally:
        other.close()
        agent.close()


def test_dose_save_writes_the_report_files(zenoh_peers, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """``fleetlink dose save`` through its own session: the robot's dose layer and map, judged on the
    map's floor; the files' contents agree with the layer."""
    peers = zenoh_peers(1)
    agent = ZenohEndpoint(session=peers[0])
    agent.start()
    keeper, pubs = _keeper_after(60.0)  # a minute under a 10 W lamp at 0.6 m: the middle reaches 100 J/m²
    try:
        with DoseShare(agent, "uvc-1", SimClock()) as share, MapShare(agent, "uvc-1", SimClock()) as maps:
            share.publish(pubs[-1])
            maps.publish(MapPublication(7, ROOM, 0.05, (0.0, 0.0), None, True))
            out = tmp_path / "report"
            args = ["dose", "save", "--robot", "uvc-1", "--out", str(out), "--connect", peers.endpoints[0]]
            assert main(args) == 0
            low = tmp_path / "low"  # judged at a round's own, lower dose: more of the floor at it
            assert main([*args[:5], str(low), *args[6:], "--target", "1"]) == 0
            assert main([*args, "--target", "0"]) == 2
            assert main(["dose", "save", "--robot", "uvc-9", "--out", str(tmp_path / "x"), "--connect",
                         peers.endpoints[0], "--timeout", "1"]) == 1  # fmt: skip
            assert main(["dose", "save", "--robot", "no/such", "--out", str(tmp_path / "x")]) == 2
    finally:
        agent.close()
    names = sorted(p.name for p in out.iterdir())
    assert names == ["dose.csv", "dose.pgm", "dose.png", "summary.json", "summary.txt"]
    summary = json.loads((out / "summary.json").read_text())
    floor = (ROOM[1:-1, 1:-1] == 0).sum() * 0.05 * 0.05  # the room's inside, 3.9 m x 2.9 m
    assert summary["floor_m2"] == pytest.approx(floor, rel=0.03)
    assert summary["reached_m2"] + summary["below_m2"] == pytest.approx(summary["floor_m2"])
    assert 0.0 < summary["reached_m2"] < summary["floor_m2"] and summary["regions_total"] >= 1
    assert summary["target_j_m2"] == 100.0 and summary["lamp_on_s"] == pytest.approx(60.0)
    assert summary["robots"][0]["robot"] == "uvc-1" and summary["floor"].startswith("the robots' maps")
    lines = (out / "dose.csv").read_text().splitlines()
    assert lines[0] == "x_m,y_m,dose_j_per_m2,at_target"
    rows = [tuple(map(float, line.split(","))) for line in lines[1:]]
    assert len(rows) * 0.01 == pytest.approx(summary["floor_m2"])
    reached = sum(0.01 for r in rows if r[3] == 1)
    assert reached == pytest.approx(summary["reached_m2"])
    centre = min(rows, key=lambda r: math.hypot(r[0] - 2.0, r[1] - 1.5))
    assert centre[2] == pytest.approx(keeper.grid.dose_at(np.array([2.0]), np.array([1.5]))[0, 0], rel=1e-6, abs=1e-3)
    pgm = (out / "dose.pgm").read_bytes()
    assert pgm.startswith(b"P5\n")
    assert (out / "dose.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    at_one = json.loads((low / "summary.json").read_text())
    assert at_one["target_j_m2"] == 10.0 and at_one["reached_m2"] > summary["reached_m2"]
    text = (out / "summary.txt").read_text()
    assert "at or above target" in text and "below target" in text and "robots: uvc-1" in text
