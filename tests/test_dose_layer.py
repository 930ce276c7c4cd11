"""The agent's dose keeper (agent/dose_layer.py), pure: the lamp's dose at a standing pose against the
closed-form point source, nothing with the lamp off, a moving robot's dose along its path against a
finely stepped reference, a standing robot reusing its footprint, unplaced lamp time, publications
that patch a receiver's copy exactly; and the ``[uv]`` table of robot.toml."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fleetlink.agent.config import ConfigError, parse_agent_config
from fleetlink.agent.dose_layer import DoseKeeper, DosePublication, DoseSample
from fleetlink.shared.dose import DoseGrid, FloorMask, Lamp
from fleetlink.shared.dose_codec import FULL_BITS, SharedDose, patch_fields, snapshot_fields, to_float32_down
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate
from fleetlink.shared.wire import HeaderCounter, decode, encode

P, H = 10.0, 0.6
LAMP = Lamp(P, H)
OPEN = FloorMask(np.ones((240, 240), dtype=bool), 0.05, (-6.0, -6.0))
"""12 m x 12 m of open floor around the origin, on the map's 0.05 m cells."""


def _point(d: float) -> float:
    """Irradiance (W/m²) of the point source at horizontal distance d: P h / (4 pi (d² + h²)^1.5)."""
    return P * H / (4.0 * math.pi * (d * d + H * H) ** 1.5)


def _run(keeper: DoseKeeper, samples: list[DoseSample]) -> list[DosePublication]:
    return [p for s in samples if (p := keeper.step(s)) is not None]


def _standing(t0: float, t1: float, x: float, y: float, *, hz: float = 20.0, on: bool = True) -> list[DoseSample]:
    n = round((t1 - t0) * hz)
    return [DoseSample(t0 + i / hz, x, y, on, True) for i in range(n + 1)]


def _keeper(**kw: float) -> DoseKeeper:
    k = DoseKeeper(LAMP, 100.0, 0.1, **kw)
    k.set_floor(OPEN, 1)
    return k


def test_lamp_on_at_a_standing_pose_gives_the_closed_form_dose() -> None:
    k = _keeper()
    # On from t = 0 (the first sample says on) to t = 30 s (the sample that says off): 30 s.
    _run(k, [*_standing(0.0, 29.95, 1.0, 2.0), DoseSample(30.0, 1.0, 2.0, False, True)])
    assert k.grid.lamp_seconds == pytest.approx(30.0, rel=1e-12)
    for d in (0.0, 0.3, 0.5, 1.0, 2.0, 3.0):
        got = k.grid.dose_at(np.array([1.0 + d]), np.array([2.0]))[0, 0]
        assert got == pytest.approx(_point(d) * 30.0, rel=1e-9), d
    # The same 1 m away in every direction (cell centres on multiples of 0.1 m).
    assert k.grid.dose_at(np.array([0.0]), np.array([2.0]))[0, 0] == pytest.approx(_point(1.0) * 30.0, rel=1e-9)
    assert k.grid.dose_at(np.array([1.0]), np.array([1.0]))[0, 0] == pytest.approx(_point(1.0) * 30.0, rel=1e-9)
    assert k.grid.dose_at(np.array([1.0]), np.array([3.0]))[0, 0] == pytest.approx(_point(1.0) * 30.0, rel=1e-9)
    assert k.unplaced_s == 0.0


def test_lamp_off_adds_nothing() -> None:
    k = _keeper()
    pubs = _run(k, _standing(0.0, 20.0, 1.0, 1.0, on=False))
    assert pubs == [] and k.grid.dose.size == 0 and k.grid.lamp_seconds == 0.0
    assert k.footprints == k.exposures == 0 and k.version == 0
    # On then off again: only the interval it was reported on counts.
    _run(k, [DoseSample(20.0, 1.0, 1.0, True, True), DoseSample(25.0, 1.0, 1.0, False, True)])
    _run(k, _standing(25.0, 40.0, 1.0, 1.0, on=False))
    assert k.grid.lamp_seconds == pytest.approx(5.0)
    assert k.grid.dose_at(np.array([1.0]), np.array([1.0]))[0, 0] == pytest.approx(_point(0.0) * 5.0, rel=1e-9)


def test_a_moving_robot_doses_its_path() -> None:
    """At 0.3 m/s along y = 0 for 10 s, lamp on: the keeper's runs (0.2 s, at their midpoints) against
    a reference stepped every 5 mm, on the cells the lamp lit well."""
    k = _keeper()
    speed, hz, seconds = 0.3, 20.0, 10.0
    n = round(seconds * hz)
    samples = [DoseSample(i / hz, -1.5 + speed * i / hz, 0.0, i < n, True) for i in range(n + 1)]  # off at 10 s
    _run(k, samples)
    ref = DoseGrid(0.1)
    step = 0.005
    for i in range(round(speed * seconds / step)):
        ref.add(LAMP, -1.5 + (i + 0.5) * step, 0.0, step / speed, OPEN)
    xs, ys = np.arange(-4.0, 4.0, 0.1), np.arange(-3.0, 3.0, 0.1)
    got, want = k.grid.dose_at(xs, ys), ref.dose_at(xs, ys)
    lit = want > 1.0
    assert lit.sum() > 500
    assert np.abs(got[lit] / want[lit] - 1.0).max() < 0.01
    assert k.grid.lamp_seconds == pytest.approx(seconds)
    # The dose along the path is far above what the same time standing at its start would give there.
    mid = k.grid.dose_at(np.array([0.0]), np.array([0.0]))[0, 0]
    assert mid == pytest.approx(ref.dose_at(np.array([0.0]), np.array([0.0]))[0, 0], rel=0.005)
    # CPU: a footprint per run (0.2 s or 0.1 m), not per sample.
    assert k.footprints == k.exposures
    assert seconds / 0.2 - 2 <= k.footprints <= seconds / 0.2 + 2


def test_standing_still_reuses_the_footprint() -> None:
    k = _keeper()
    rng = np.random.default_rng(3)
    jitter = rng.uniform(-0.004, 0.004, size=(401, 2))  # fused-pose noise of a robot standing still
    samples = [DoseSample(i / 20.0, 1.0 + jitter[i, 0], 1.0 + jitter[i, 1], True, True) for i in range(401)]
    _run(k, samples)
    assert k.exposures >= 90 and k.footprints == 1
    assert k.grid.lamp_seconds == pytest.approx(20.0)
    # The same dose as exposing the one footprint for the whole time (reuse is exact scaling).
    assert k.grid.dose_at(np.array([1.0]), np.array([1.0]))[0, 0] == pytest.approx(
        20.0 * k.grid.footprint(LAMP, *_first_footprint_xy(samples), OPEN).irradiance.max(), rel=1e-9
    )
    # A new map (floor version) makes a new footprint; moving 5 cm does too (one for the run across
    # the step, one where it stands now), then it is reused again.
    k.set_floor(OPEN, 2)
    _run(k, _standing(20.05, 21.0, 1.0, 1.0))
    assert k.footprints == 2
    _run(k, _standing(21.05, 25.0, 1.05, 1.0))
    assert k.footprints == 4


def _first_footprint_xy(samples: list[DoseSample]) -> tuple[float, float]:
    """Where the keeper put its one footprint: the midpoint of the first run (the first 0.2 s)."""
    a, b = samples[0], samples[4]
    return 0.5 * (a.x + b.x), 0.5 * (a.y + b.y)


def test_unplaced_lamp_time_is_counted_not_placed() -> None:
    k = DoseKeeper(LAMP, 100.0, 0.1)  # no floor (no site-frame map) yet
    _run(k, _standing(0.0, 5.0, 1.0, 1.0))
    assert k.unplaced_s == pytest.approx(5.0) and k.grid.dose.size == 0
    k.set_floor(OPEN, 1)
    _run(k, [DoseSample(5.0 + i / 20.0, 1.0, 1.0, True, False) for i in range(1, 41)])  # not localised
    assert k.unplaced_s == pytest.approx(7.0) and k.grid.dose.size == 0
    pubs = _run(k, [*_standing(7.05, 10.0, 1.0, 1.0), DoseSample(10.0, 1.0, 1.0, False, True)])
    assert k.unplaced_s == pytest.approx(7.05) and k.grid.lamp_seconds == pytest.approx(2.95)
    assert pubs and pubs[-1].unplaced_s == pytest.approx(k.unplaced_s)


def test_publications_patch_a_receivers_copy() -> None:
    """Through the wire: the first publication as a snapshot, then each as a patch on the copy; the
    copy ends equal to the keeper's grid rounded down to float32; at most one a second."""
    k = _keeper()
    counter = HeaderCounter(_Clock(), robot="uvc-1", sender="agent-uvc-1")
    samples = [DoseSample(i / 20.0, 0.1 * i / 20.0, 0.0, True, True) for i in range(20 * 12)]
    pubs = _run(k, samples)
    assert 10 <= len(pubs) <= 12 and all(b.version > a.version for a, b in itertools.pairwise(pubs))
    first = pubs[0]
    fields = snapshot_fields(
        first.dose, first.resolution, first.origin, first.version,
        target_j_m2=100.0, lamp_on_s=first.lamp_on_s, unplaced_s=0.0, lamp=first.lamp,
    )  # fmt: skip
    assert fields is not None and fields["mantissa_bits"] == FULL_BITS
    copy = SharedDose.from_snapshot(decode(DoseSnapshot, encode(counter.make(DoseSnapshot, **fields))))
    for prev, pub in itertools.pairwise(pubs):
        assert pub.changed is not None  # the grid did not grow: a patch each time
        f = patch_fields(
            pub.dose, pub.resolution, pub.origin, pub.changed, pub.version, prev.version,
            target_j_m2=100.0, lamp_on_s=pub.lamp_on_s, unplaced_s=0.0,
        )  # fmt: skip
        assert f is not None
        assert copy.apply(decode(DoseUpdate, encode(counter.make(DoseUpdate, **f))))
    last = pubs[-1]
    assert copy.version == last.version and copy.lamp_on_s == pytest.approx(last.lamp_on_s)
    assert np.array_equal(copy.cells, to_float32_down(last.dose))
    assert (copy.cells.astype(np.float64) <= last.dose).all()  # never more than the agent counted


class _Clock:
    def now(self) -> float:
        return 0.0

    def wall(self) -> float:
        return 1_767_225_600.0


# -- configuration ---------------------------------------------------------------------------------

BASE = {"robot": "uvc-1", "board": "socket://127.0.0.1:7001", "zenoh": {}}


def test_uv_table_configures_the_lamp_and_target() -> None:
    cfg = parse_agent_config({**BASE, "uv": {"uvc_power_w": 12.5, "height_m": 0.9, "tube_length_m": 0.8}})
    assert cfg.uv is not None
    assert cfg.uv.lamp == Lamp(12.5, 0.9, 0.8)
    assert cfg.uv.target_j_m2 == 100.0 and cfg.uv.dose_resolution_m == 0.1
    assert parse_agent_config(BASE).uv is None  # no table: no lamp, no dose layer
    cfg = parse_agent_config({**BASE, "uv": {"uvc_power_w": 10, "height_m": 0.6, "target_dose_mj_cm2": 22}})
    assert cfg.uv is not None and cfg.uv.target_j_m2 == 220.0


@pytest.mark.parametrize(
    ("uv", "says"),
    [
        ({"uvc_power_w": 0.0, "height_m": 0.6}, "uv.uvc_power_w: must be >= 0.001, got 0.0"),
        ({"uvc_power_w": -3.0, "height_m": 0.6}, "uv.uvc_power_w: must be >= 0.001"),
        ({"uvc_power_w": math.nan, "height_m": 0.6}, "uv.uvc_power_w: must be finite, got nan"),
        ({"uvc_power_w": 10.0, "height_m": 0.2}, "uv.height_m: the lamp is 0.2 m above the floor, nearer than"),
        ({"uvc_power_w": 10.0, "height_m": 0.6, "target_dose_mj_cm2": 0.0}, "uv.target_dose_mj_cm2: must be >="),
        (
            {"uvc_power_w": 10.0, "height_m": 0.6, "target_dose_mj_cm2": math.nan},
            "uv.target_dose_mj_cm2: must be finite",
        ),
        ({"uvc_power_w": 10.0, "height_m": 0.6, "dose_resolution_m": 0.0}, "uv.dose_resolution_m: must be >="),
        ({"height_m": 0.6}, "uv.uvc_power_w: missing required key"),
    ],
)
def test_bad_uv_values_are_refused_with_their_key(uv: dict[str, float], says: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_agent_config({**BASE, "uv": uv}, "robot.toml")
    assert f"robot.toml: {says}" in str(err.value)


def test_the_keeper_refuses_a_bad_target() -> None:
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="target dose must be a finite number > 0"):
            DoseKeeper(LAMP, bad)
