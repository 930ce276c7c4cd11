from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from fleetlink.field.floor import ray_cast
from fleetlink.field.mapserver import (
    MapError,
    OccupancyMap,
    boundary_segments,
    grid_from_image,
    image_from_grid,
    parse_map_yaml,
    read_map,
    read_pgm,
    write_map,
    write_pgm,
)
from fleetlink.field.plans import PlanError, load_plan, plan_from_map

# -- writing as map_saver does ---------------------------------------------------------------------


def test_write_map_matches_map_saver_bytes(tmp_path: Path) -> None:
    grid = np.array([[0, 100, -1], [100, 0, 0]], dtype=np.int8)  # row 0 = bottom
    yaml = write_map(grid, 0.05, (-1.5, 2.25, 0.0), tmp_path)
    assert yaml == tmp_path / "map.yaml"
    data = (tmp_path / "map.pgm").read_bytes()
    header = b"P5\n# CREATOR: fleetlink mapserver.py 0.050 m/pix\n3 2\n255\n"
    assert data == header + bytes([0, 254, 254, 254, 0, 205])  # top row first: the grid's row 1
    assert yaml.read_text() == (
        "image: map.pgm\n"
        "resolution: 0.050000\n"
        "origin: [-1.500000, 2.250000, 0.000000]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
        "\n"
    )


def test_write_map_uses_map_savers_thresholds_for_probabilities(tmp_path: Path) -> None:
    grid = np.array([[0, 25, 26, 64, 65, 100, -1]], dtype=np.int8)
    write_map(grid, 0.1, (0.0, 0.0), tmp_path, name="p")
    assert read_pgm(tmp_path / "p.pgm").tolist() == [[254, 254, 205, 205, 0, 0, 205]]


@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (64, 48)])
def test_trinary_round_trip(tmp_path: Path, shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(shape))
    grid = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=shape)
    yaml = write_map(grid, 0.025, (-3.0, -4.5, 0.25), tmp_path / "maps" / "floor2")
    assert yaml == tmp_path / "maps" / "floor2.yaml" and (tmp_path / "maps" / "floor2.pgm").is_file()
    m = read_map(yaml)
    assert m.grid.dtype == np.int8 and np.array_equal(m.grid, grid)
    assert m.resolution == 0.025 and m.origin == (-3.0, -4.5, 0.25)
    assert (m.width, m.height) == (shape[1], shape[0])
    assert np.array_equal(m.image, image_from_grid(grid))
    assert not m.negate and m.mode == "trinary" and m.occupied_thresh == 0.65 and m.free_thresh == 0.196


def test_write_map_keeps_precision_where_percent_f_would_lose_it(tmp_path: Path) -> None:
    yaml = write_map(np.zeros((2, 2), dtype=np.int8), 0.0123456789, (1e-7, -2.0, math.pi), tmp_path, name="fine")
    text = yaml.read_text()
    assert "resolution: 0.0123456789\n" in text and "origin: [1e-07, -2.000000, 3.141592653589793]" in text
    m = read_map(yaml)
    assert m.resolution == 0.0123456789 and m.origin == (1e-7, -2.0, math.pi)


def test_write_map_refuses_bad_input(tmp_path: Path) -> None:
    with pytest.raises(MapError, match=r"grid: cells must be -1 \(unknown\) or 0-100, found 0\.\.254"):
        write_map(np.array([[0, 254]], dtype=np.uint8), 0.05, (0, 0, 0), tmp_path)
    with pytest.raises(MapError, match="grid: expected integer cells"):
        write_map(np.zeros((2, 2)), 0.05, (0, 0, 0), tmp_path)
    with pytest.raises(MapError, match="grid: expected a non-empty 2-D array"):
        write_map(np.zeros(4, dtype=np.int8), 0.05, (0, 0, 0), tmp_path)
    with pytest.raises(MapError, match="resolution: must be a finite number > 0"):
        write_map(np.zeros((2, 2), dtype=np.int8), 0.0, (0, 0, 0), tmp_path)
    with pytest.raises(MapError, match="origin: expected finite"):
        write_map(np.zeros((2, 2), dtype=np.int8), 0.05, (0, math.nan, 0), tmp_path)


# -- reading as image_loader does ------------------------------------------------------------------


def _write_pair(tmp_path: Path, pgm: bytes, yaml: str, name: str = "m") -> Path:
    (tmp_path / f"{name}.pgm").write_bytes(pgm)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml)
    return path


def test_ascii_pgm_with_negate(tmp_path: Path) -> None:
    # P2 with comments in the header and between pixels; with negate, black is free and white occupied.
    pgm = b"P2\n# made by hand\n3 2 # width height\n# maxval next\n255\n0 255 128\n# second row\n10 240 205\n"
    yaml = _write_pair(tmp_path, pgm, "image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 1\n")
    m = read_map(yaml)
    assert m.negate
    assert m.image.tolist() == [[0, 255, 128], [10, 240, 205]]
    # negate: p = v / 255 -> 0: free, 255: occupied, 128 (0.502): unknown, 10: free, 240: occupied, 205 (0.804): occupied
    assert m.grid.tolist() == [[0, 100, 100], [0, 100, -1]]  # row 0 is the bottom row of the picture


def test_scale_and_raw_modes(tmp_path: Path) -> None:
    pixels = bytes([0, 50, 100, 128, 160, 200, 205, 254, 255])
    pgm = b"P5\n9 1\n255\n" + pixels
    scale = read_map(_write_pair(tmp_path, pgm, "image: m.pgm\nresolution: 1\norigin: [0, 0, 0]\nmode: scale\n"))
    # occupied above 0.65, free below 0.196, else 1 + 98 * (p - free) / (occ - free), truncated
    assert scale.grid.tolist() == [[100, 100, 89, 66, 39, 5, 1, 0, 0]]
    raw = read_map(_write_pair(tmp_path, pgm, "image: m.pgm\nresolution: 1\norigin: [0, 0, 0]\nmode: raw\n", "r"))
    assert raw.grid.tolist() == [[0, 50, 100, -128, -96, -56, -51, -2, -1]]  # pixel values as signed bytes
    trinary = grid_from_image(np.frombuffer(pixels, dtype=np.uint8).reshape(1, 9))
    assert trinary.tolist() == [[100, 100, -1, -1, -1, -1, -1, 0, 0]]


def test_thresholds_are_strict_as_in_image_loader() -> None:
    # p = (255 - 89) / 255 = 0.651 > 0.65 -> occupied; p = (255 - 90) / 255 = 0.647 -> unknown
    assert grid_from_image(np.array([[89, 90]], dtype=np.uint8)).tolist() == [[100, -1]]
    # with free_thresh 0.5: p = 0.5 exactly is not below it -> unknown
    img = np.array([[255 - 127.5]])
    assert grid_from_image(img, free_thresh=0.5).tolist() == [[-1]]


def test_binary_pgm_header_comments_16_bit_and_small_maxval(tmp_path: Path) -> None:
    p8 = tmp_path / "c.pgm"
    p8.write_bytes(b"P5 # magic\n# a comment line\n2\n# between\n1\n255\n" + bytes([7, 250]))
    assert read_pgm(p8).tolist() == [[7, 250]]
    p16 = tmp_path / "w.pgm"
    p16.write_bytes(b"P5\n2 1\n65535\n" + (0).to_bytes(2, "big") + (65535).to_bytes(2, "big"))
    img = read_pgm(p16)
    assert img.dtype == np.uint16 and img.tolist() == [[0, 65535]]
    yaml = tmp_path / "w.yaml"
    yaml.write_text("image: w.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n")
    assert read_map(yaml).grid.tolist() == [[100, 0]]
    p4 = tmp_path / "s.pgm"
    p4.write_bytes(b"P5\n3 1\n15\n" + bytes([0, 15, 8]))  # scaled to 0-255 as SDL_image does: 8 -> 136
    yaml.write_text("image: s.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n")
    assert read_map(yaml).grid.tolist() == [[100, 0, -1]]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\x89PNG\r\n\x1a\n....", "PNG images are not supported"),
        (b"P6\n1 1\n255\n\x00\x00\x00", "not a PGM image (expected P5 or P2"),
        (b"P5\n2 2\n255\n\x00\x00\x00", "truncated: expected 4 bytes of pixels for 2 x 2, found 3"),
        (b"P5\n2 x\n255\n\x00\x00", "PGM header: expected the height"),
        (b"P5\n2 1\n100\n\x00\xff", "a pixel value (255) exceeds maxval 100"),
        (b"P5\n0 1\n255\n", "width and height must be positive"),
        (b"P2\n2 1\n255\n0\n", "truncated: expected 2 pixel values"),
        (b"P2\n2 1\n255\n0 300\n", "values must be 0..255"),
    ],
)
def test_bad_images_are_refused_with_the_reason(tmp_path: Path, data: bytes, message: str) -> None:
    path = tmp_path / "bad.pgm"
    path.write_bytes(data)
    with pytest.raises(MapError) as err:
        read_pgm(path)
    assert message in str(err.value) and "bad.pgm" in str(err.value)


def test_write_pgm_round_trip(tmp_path: Path) -> None:
    img = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    path = write_pgm(tmp_path / "x.pgm", img, comment="hello")
    assert path.read_bytes().startswith(b"P5\n# hello\n4 3\n255\n")
    assert np.array_equal(read_pgm(path), img)


# -- YAML ------------------------------------------------------------------------------------------


def test_yaml_parser_handles_what_map_server_files_contain(tmp_path: Path) -> None:
    text = (
        "---\n"
        "# saved by hand\n"
        "image: 'my map.pgm'   # a quoted name with a space\n"
        "resolution: 0.1\n"
        "origin:\n"
        "  - -1.5\n"
        "  - 2.0\n"
        "  - 0.0\n"
        "negate: true\n"
        "occupied_thresh: 0.7\n"
        "free_thresh: 0.2\n"
        'mode: "scale"\n'
        "unknown_tool_key: whatever # ignored\n"
    )
    meta = parse_map_yaml(text, "x.yaml", tmp_path)
    assert meta.image == tmp_path / "my map.pgm"
    assert meta.resolution == 0.1 and meta.origin == (-1.5, 2.0, 0.0)
    assert meta.negate and meta.occupied_thresh == 0.7 and meta.free_thresh == 0.2 and meta.mode == "scale"
    defaults = parse_map_yaml("image: /abs/m.pgm\nresolution: 0.05\norigin: [1, 2, 3]\n", "y.yaml", tmp_path)
    assert defaults.image == Path("/abs/m.pgm") and defaults.origin == (1.0, 2.0, 3.0)
    assert not defaults.negate and defaults.occupied_thresh == 0.65 and defaults.free_thresh == 0.196
    assert defaults.mode == "trinary"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("image: m.pgm\norigin: [0, 0, 0]\n", "x.yaml: missing key resolution"),
        ("resolution: 0.05\norigin: [0, 0, 0]\n", "x.yaml: missing key image"),
        ("image: m.pgm\nresolution: fine\norigin: [0, 0, 0]\n", "x.yaml: resolution: expected a number, got 'fine'"),
        ("image: m.pgm\nresolution: -0.05\norigin: [0, 0, 0]\n", "x.yaml: resolution: must be > 0"),
        ("image: m.pgm\nresolution: .nan\norigin: [0, 0, 0]\n", "x.yaml: resolution: expected a number"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, x]\n", "x.yaml: origin[2]: expected a number, got 'x'"),
        ("image: m.pgm\nresolution: 0.05\norigin: 3\n", "x.yaml: origin: expected [x, y, yaw]"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0\n", "x.yaml: origin: expected a list like [x, y, yaw]"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 2\n", "x.yaml: negate: expected 0 or 1"),
        (
            "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: fancy\n",
            "x.yaml: mode: expected one of trinary, scale, raw",
        ),
        (
            "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nfree_thresh: 1.5\n",
            "x.yaml: free_thresh: must be between 0 and 1",
        ),
        (
            "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nfree_thresh: 0.7\n",
            "x.yaml: free_thresh: must not exceed occupied_thresh",
        ),
        ("image: m.pgm\nimage: n.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "x.yaml: image: appears twice"),
        ("image: m.pgm\nresolution 0.05\n", "x.yaml: line 2: expected 'key: value'"),
        ("image: 'm.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "x.yaml: image: unterminated quoted string"),
    ],
)
def test_yaml_errors_name_the_key(text: str, message: str) -> None:
    with pytest.raises(MapError) as err:
        parse_map_yaml(text, "x.yaml")
    assert message in str(err.value)


def test_missing_image_names_the_key(tmp_path: Path) -> None:
    yaml = tmp_path / "m.yaml"
    yaml.write_text("image: nowhere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapError, match=r"m\.yaml: image: no such file .*nowhere\.pgm"):
        read_map(yaml)


# -- walls from grids ------------------------------------------------------------------------------


def _rooms(size: int = 200) -> npt.NDArray[np.int8]:
    """Unknown outside; a 2-cell-thick outer wall; an interior wall with a doorway; a side room; a table."""
    g = np.full((size, size), -1, dtype=np.int8)
    lo, hi = size // 20, size - size // 20  # 10 .. 190 for 200
    g[lo:hi, lo:hi] = 100
    g[lo + 2 : hi - 2, lo + 2 : hi - 2] = 0
    mid = size // 2
    g[lo + 2 : hi - 2, mid : mid + 2] = 100  # interior wall, x = mid * res
    g[mid - 10 : mid + 6, mid : mid + 2] = 0  # its doorway (16 cells = 0.8 m at 5 cm)
    g[int(size * 0.7) : int(size * 0.7) + 2, lo + 2 : mid] = 100  # a side room in the west half
    g[int(size * 0.7) : int(size * 0.7) + 2, size // 5 : size // 5 + 16] = 0  # its doorway
    g[size // 4 : size // 4 + 10, int(size * 0.65) : int(size * 0.75)] = 100  # a table
    return g


def _check_segments_lie_on_boundaries(
    blocked: npt.NDArray[np.bool_], segs: npt.NDArray[np.float64], res: float
) -> None:
    h, w = blocked.shape

    def cell(r: int, c: int) -> bool:
        return bool(blocked[r, c]) if 0 <= r < h and 0 <= c < w else True

    for x1, y1, x2, y2 in segs / res:
        assert x1 == x2 or y1 == y2
        for t in np.linspace(0.0, 1.0, 5)[1:-1]:  # sample inside the segment
            u, v = x1 + t * (x2 - x1), y1 + t * (y2 - y1)
            if y1 == y2:  # horizontal: the cells below and above differ
                c, k = math.floor(u), round(v)
                assert cell(k - 1, c) != cell(k, c)
            else:
                r, k = math.floor(v), round(u)
                assert cell(r, k - 1) != cell(r, k)


def test_boundary_segments_follow_cell_edges_and_merge_runs() -> None:
    g = _rooms(200)
    occ = OccupancyMap(grid=g, resolution=0.05, origin=(0.0, 0.0, 0.0), image=image_from_grid(g))
    segs = occ.segments()
    assert 10 < len(segs) < 80  # a few dozen, not the ~3000 cell edges
    _check_segments_lie_on_boundaries(occ.blocked(), segs, 0.05)
    only_occupied = occ.segments(unknown_is_wall=False)
    _check_segments_lie_on_boundaries(occ.blocked(False), only_occupied, 0.05)
    assert len(only_occupied) > len(segs)  # now the outer wall's outside face counts too


def test_segment_count_stays_small_for_a_large_map() -> None:
    g = np.zeros((400, 400), dtype=np.int8)
    g[:, :2] = g[:, -2:] = g[:2, :] = g[-2:, :] = 100
    for k in range(50, 400, 50):  # a 7 x 7 grid of rooms with doorways
        g[:, k : k + 2] = 100
        g[k : k + 2, :] = 100
        for j in range(20, 400, 50):
            g[j : j + 10, k : k + 2] = 0
            g[k : k + 2, j : j + 10] = 0
    segs = boundary_segments(g == 100, 0.05)
    cell_edges = int(np.sum((g[1:] == 100) != (g[:-1] == 100)) + np.sum((g[:, 1:] == 100) != (g[:, :-1] == 100)))
    assert cell_edges > 10_000
    assert 100 < len(segs) < 1_000


def test_boundary_segments_respect_origin_and_yaw() -> None:
    segs = boundary_segments(np.zeros((1, 1), dtype=bool), 0.5, (1.0, 2.0, math.pi / 2))
    xs, ys = np.concatenate([segs[:, 0], segs[:, 2]]), np.concatenate([segs[:, 1], segs[:, 3]])
    assert len(segs) == 4
    assert xs.min() == pytest.approx(0.5) and xs.max() == pytest.approx(1.0)
    assert ys.min() == pytest.approx(2.0) and ys.max() == pytest.approx(2.5)
    occ = OccupancyMap(
        grid=np.zeros((2, 4), np.int8), resolution=0.5, origin=(1.0, 2.0, math.pi / 2), image=np.zeros((2, 4), np.uint8)
    )
    x, y = occ.cell_center(3, 1)
    assert (x, y) == pytest.approx((1.0 - 0.75, 2.0 + 1.75))
    assert occ.cell_of(x, y) == (3, 1)


def test_a_map_server_map_loads_as_a_plan_whose_walls_stop_rays(tmp_path: Path) -> None:
    g = _rooms(200)  # 10 m x 10 m at 5 cm, origin (-1, -2)
    yaml = write_map(g, 0.05, (-1.0, -2.0, 0.0), tmp_path, name="lab")
    plan = load_plan(yaml)
    assert plan.name == "lab" and plan.bounds == pytest.approx((-1.0, -2.0, 9.0, 8.0))
    assert not plan.starts and not plan.anchors
    segs = plan.segments()
    walls = [(float(a), float(b), float(c), float(d)) for a, b, c, d in segs]
    # From (x 1.5, y 1.525) (cell 50, 70): the interior wall (cells 100-101) is 2.5 m east,
    # the outer wall's inner face (cell 12 ends at x = -1 + 12 * 0.05 = -0.4) 1.9 m west.
    assert ray_cast(walls, 1.5, 1.525, 0.0, 20.0) == pytest.approx(2.5)
    assert ray_cast(walls, 1.5, 1.525, math.pi, 20.0) == pytest.approx(1.9)
    # Through the doorway (rows 90-105 are open) the ray crosses into the east half.
    assert ray_cast(walls, 1.5, 2.975, 0.0, 20.0) == pytest.approx(8.4 - 1.5)
    # Every blocked cell is behind a wall: a ray from a free cell stops before reaching it.
    rng = np.random.default_rng(1)
    free = np.argwhere(g == 0)
    for r, c in free[rng.choice(len(free), 30, replace=False)]:
        x, y = -1.0 + (c + 0.5) * 0.05, -2.0 + (r + 0.5) * 0.05
        for angle in np.linspace(0, 2 * math.pi, 12, endpoint=False):
            d = ray_cast(walls, x, y, float(angle), 20.0)
            assert math.isfinite(d)
            hx, hy = x + (d - 0.01) * math.cos(angle), y + (d - 0.01) * math.sin(angle)
            assert g[math.floor((hy + 2.0) / 0.05), math.floor((hx + 1.0) / 0.05)] == 0


def test_map_plan_sidecar_adds_starts_doors_and_anchors(tmp_path: Path) -> None:
    g = _rooms(200)
    yaml = write_map(g, 0.05, (0.0, 0.0, 0.0), tmp_path, name="lab")
    sidecar = tmp_path / "lab.plan.toml"
    sidecar.write_text(
        'name = "lab-1"\n'
        "[doors]\n"
        "east = [5.0, 4.5, 5.0, 5.3]\n"
        "[starts]\n"
        "home = { x = 2.5, y = 2.5, theta_deg = 0.0 }\n"
        "[[anchors]]\n"
        'id = "A1"\nx = 0.5\ny = 0.5\nz = 2.4\n'
    )
    plan = load_plan(yaml)
    assert plan.name == "lab-1" and plan.starts["home"].x == 2.5 and plan.anchors[0].id == "A1"
    assert ray_cast(plan.segments(), 2.5, 4.9, 0.0, 20.0) > 5.0
    assert ray_cast(plan.segments(["east"]), 2.5, 4.9, 0.0, 20.0) == pytest.approx(2.5)
    sidecar.write_text("bounds = [0, 0, 1, 1]\n")
    with pytest.raises(PlanError, match=r"lab\.plan\.toml: bounds: unknown key; allowed: access_points, anchors"):
        load_plan(yaml)
    sidecar.write_text("[starts]\nwall = { x = 0.55, y = 2.5, theta_deg = 0.0 }\n")
    with pytest.raises(PlanError, match=r"starts\.wall: \(0\.55, 2\.5\) is 0\.050 m from walls\["):
        load_plan(yaml)
    sidecar.write_text("unknown_is_wall = false\n")
    assert len(load_plan(yaml).walls) == len(plan_from_map(read_map(yaml), unknown_is_wall=False).walls)
    sidecar.write_text("unknown_is_wall = 1\n")
    with pytest.raises(PlanError, match="unknown_is_wall: expected true or false"):
        load_plan(yaml)


def test_map_errors_surface_as_plan_errors(tmp_path: Path) -> None:
    yaml = tmp_path / "m.yaml"
    yaml.write_text("image: m.pgm\nresolution: 0.05\n")
    with pytest.raises(PlanError, match=r"m\.yaml: missing key origin"):
        load_plan(yaml)


def test_rasterised_plan_round_trips_through_a_map(tmp_path: Path) -> None:
    plan = load_plan("apartment")
    occ = plan.to_grid(0.05)
    assert occ.grid.shape == (162, 202) and set(np.unique(occ.grid)) == {0, 100}
    yaml = write_map(occ.grid, occ.resolution, occ.origin, tmp_path, name="apt")
    again = plan_from_map(read_map(yaml), name="apt")
    # Walls drawn one cell thick come back within a cell or two of where they were.
    diffs = []
    for pose in plan.starts.values():
        for angle in np.linspace(0, 2 * math.pi, 24, endpoint=False):
            a = ray_cast(plan.segments(), pose.x, pose.y, float(angle), 30.0)
            b = ray_cast(again.segments(), pose.x, pose.y, float(angle), 30.0)
            diffs.append(abs(a - b))
    assert np.median(diffs) < 0.05 and np.percentile(diffs, 90) < 0.15


def test_the_example_map_is_the_apartment() -> None:
    plan = load_plan("apartment-map")
    ref = load_plan("apartment")
    assert set(plan.starts) == set(ref.starts) and set(plan.doors) == set(ref.doors)
    assert len(plan.anchors) == len(ref.anchors)
    assert len(plan.walls) < 150
    dock = plan.starts["dock"]
    assert ray_cast(plan.segments(), dock.x, dock.y, -math.pi / 2, 5.0) == pytest.approx(0.35)
