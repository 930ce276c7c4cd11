"""ROS map_server maps (a PGM image and a YAML file): read them, write them, and turn them into walls.

Pure functions on numpy arrays and files; no ROS, no PyYAML, no image library.

Reading follows map_server's ``image_loader.cpp`` (ROS 1 noetic): for each pixel value ``v``,
``p = (255 - v) / 255`` (``p = v / 255`` when ``negate``); ``p > occupied_thresh`` is occupied (100),
``p < free_thresh`` is free (0), anything else unknown (-1) in ``trinary`` mode, ``1 + 98 * ratio``
(truncated) in ``scale`` mode, and in ``raw`` mode the pixel value itself, stored as a signed byte
(so 255 reads as -1, as in ROS). Image rows are flipped: the grid's cell ``[0, 0]`` (row 0, column 0)
is the bottom-left pixel, and ``origin`` is the pose of that cell's lower-left corner.

Writing follows ``map_saver.cpp``: a binary ``P5`` PGM with 254 for free, 0 for occupied and 205
for unknown, and a YAML file with ``image``, ``resolution``, ``origin``, ``negate: 0``,
``occupied_thresh: 0.65`` and ``free_thresh: 0.196``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

__all__ = [
    "FREE",
    "MODES",
    "OCCUPIED",
    "UNKNOWN",
    "MapError",
    "MapYaml",
    "OccupancyMap",
    "boundary_segments",
    "grid_from_image",
    "image_from_grid",
    "parse_map_yaml",
    "read_map",
    "read_pgm",
    "to_8bit",
    "write_map",
    "write_pgm",
]

FREE = 0
OCCUPIED = 100
UNKNOWN = -1
MODES = ("trinary", "scale", "raw")

# map_saver's pixel values and its default thresholds on the grid's 0-100 values (noetic: --free 25, --occ 65).
PGM_FREE = 254
PGM_OCCUPIED = 0
PGM_UNKNOWN = 205
SAVER_THRESHOLD_FREE = 25
SAVER_THRESHOLD_OCCUPIED = 65

Origin = tuple[float, float, float]


class MapError(ValueError):
    """A map file (YAML or image) that cannot be used, with the file, the key and the reason."""


@dataclass(frozen=True, slots=True)
class MapYaml:
    """The YAML half of a map_server map. ``image`` is resolved against the YAML file's folder."""

    image: Path
    resolution: float
    origin: Origin
    negate: bool = False
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    mode: str = "trinary"


@dataclass(frozen=True, slots=True, eq=False)
class OccupancyMap:
    """An occupancy grid as map_server would publish it.

    ``grid`` is int8 with shape (height, width): row 0 is the bottom (south) row, column 0 the west
    column; -1 unknown, 0 free, 100 occupied (scale mode: 1-99 in between; raw mode: the pixel
    values as signed bytes). ``image`` holds the pixels exactly as stored in the file (row 0 = top;
    uint8, or uint16 for 16-bit PGMs).
    """

    grid: npt.NDArray[np.int8]
    resolution: float
    origin: Origin
    image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16]
    negate: bool = False
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    mode: str = "trinary"
    source: str = "<memory>"

    @property
    def width(self) -> int:
        return int(self.grid.shape[1])

    @property
    def height(self) -> int:
        return int(self.grid.shape[0])

    def cell_center(self, col: int, row: int) -> tuple[float, float]:
        """World coordinates (m) of a cell's centre."""
        return _to_world(self.origin, self.resolution, col + 0.5, row + 0.5)

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(col, row) of the cell holding a world point; may lie outside the grid."""
        ox, oy, yaw = self.origin
        dx, dy = x - ox, y - oy
        c, s = math.cos(yaw), math.sin(yaw)
        u, v = (c * dx + s * dy) / self.resolution, (-s * dx + c * dy) / self.resolution
        return math.floor(u), math.floor(v)

    def blocked(self, unknown_is_wall: bool = True) -> npt.NDArray[np.bool_]:
        """Cells a robot cannot enter: occupied ones (>= occupied value 65 in scale mode), and unknown ones if asked."""
        g = self.grid.astype(np.int16)
        occupied = g >= SAVER_THRESHOLD_OCCUPIED
        return occupied | (g < 0) if unknown_is_wall else occupied

    def segments(self, unknown_is_wall: bool = True) -> npt.NDArray[np.float64]:
        """Walls (N, 4) along the boundaries between blocked and open cells; see :func:`boundary_segments`."""
        return boundary_segments(self.blocked(unknown_is_wall), self.resolution, self.origin)


# -- YAML ------------------------------------------------------------------------------------------

_KEY = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*:(?:\s+(.*))?$")


def _strip_comment(line: str) -> str:
    """Drop a ``#`` comment that starts the line or follows whitespace, outside quotes."""
    quote = ""
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = ""
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i]
    return line


def _unquote(text: str, where: str) -> str:
    t = text.strip()
    if len(t) >= 2 and t[0] == t[-1] and t[0] in "'\"":
        inner = t[1:-1]
        if t[0] == "'":
            return inner.replace("''", "'")
        return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), inner)
    if t[:1] in ("'", '"'):
        raise MapError(f"{where}: unterminated quoted string {t!r}")
    return t


def _yaml_items(text: str, source: str) -> dict[str, str | list[str]]:
    """``key: value`` lines, flow lists ``[a, b]`` and block lists (``- a`` lines) into strings."""
    items: dict[str, str | list[str]] = {}
    block_key: str | None = None
    for lineno, raw in enumerate(text.lstrip("\ufeff").splitlines(), 1):
        line = _strip_comment(raw).rstrip()
        if not line.strip() or line.strip() in ("---", "..."):
            continue
        stripped = line.strip()
        if stripped.startswith("- ") or stripped == "-":
            if block_key is None:
                raise MapError(f"{source}: line {lineno}: a list item outside a key: {raw.strip()!r}")
            value = items[block_key]
            assert isinstance(value, list)
            value.append(stripped[1:].strip())
            continue
        m = _KEY.match(line)
        if m is None or line[0] in " \t":
            raise MapError(f"{source}: line {lineno}: expected 'key: value', got {raw.strip()!r}")
        key, value_text = m.group(1), (m.group(2) or "").strip()
        if key in items:
            raise MapError(f"{source}: {key}: appears twice (line {lineno})")
        if not value_text:
            items[key] = []
            block_key = key
            continue
        block_key = None
        if value_text.startswith("["):
            if not value_text.endswith("]"):
                raise MapError(f"{source}: {key}: expected a list like [x, y, yaw] on one line")
            body = value_text[1:-1].strip()
            items[key] = [v.strip() for v in body.split(",")] if body else []
        else:
            items[key] = value_text
    return items


def _yaml_number(items: Mapping[str, str | list[str]], key: str, source: str, default: float | None) -> float:
    if key not in items:
        if default is None:
            raise MapError(f"{source}: missing key {key}")
        return default
    value = items[key]
    if isinstance(value, list):
        raise MapError(f"{source}: {key}: expected a number, got a list")
    try:
        number = float(_unquote(value, f"{source}: {key}"))
    except ValueError:
        raise MapError(f"{source}: {key}: expected a number, got {value!r}") from None
    if not math.isfinite(number):
        raise MapError(f"{source}: {key}: must be finite, got {value!r}")
    return number


def parse_map_yaml(text: str, source: str = "<memory>", base: Path | None = None) -> MapYaml:
    """Parse a map_server YAML file's text. ``image`` is resolved against ``base`` when relative.

    Keys map_server does not know are ignored (other tools add their own); ``negate`` and the
    thresholds default to map_saver's values when absent.
    """
    items = _yaml_items(text, source)
    for key in ("image", "resolution", "origin"):
        if key not in items:
            raise MapError(f"{source}: missing key {key}")
    image_value = items["image"]
    if isinstance(image_value, list) or not _unquote(image_value, f"{source}: image"):
        raise MapError(f"{source}: image: expected the image file's name")
    image = Path(_unquote(image_value, f"{source}: image")).expanduser()
    if base is not None and not image.is_absolute():
        image = base / image
    resolution = _yaml_number(items, "resolution", source, None)
    if resolution <= 0:
        raise MapError(f"{source}: resolution: must be > 0 m per pixel, got {resolution}")
    origin_value = items["origin"]
    if not isinstance(origin_value, list) or len(origin_value) not in (2, 3):
        raise MapError(f"{source}: origin: expected [x, y, yaw], got {origin_value!r}")
    origin: list[float] = []
    for i, v in enumerate(origin_value):
        try:
            number = float(_unquote(v, f"{source}: origin[{i}]"))
        except ValueError:
            raise MapError(f"{source}: origin[{i}]: expected a number, got {v!r}") from None
        if not math.isfinite(number):
            raise MapError(f"{source}: origin[{i}]: must be finite, got {v!r}")
        origin.append(number)
    if len(origin) == 2:
        origin.append(0.0)
    negate_value = items.get("negate", "0")
    negate_text = negate_value if isinstance(negate_value, str) else "?"
    negate_text = _unquote(negate_text, f"{source}: negate").lower()
    if negate_text not in ("0", "1", "true", "false"):
        raise MapError(f"{source}: negate: expected 0 or 1, got {negate_value!r}")
    occupied = _yaml_number(items, "occupied_thresh", source, 0.65)
    free = _yaml_number(items, "free_thresh", source, 0.196)
    for key, value in (("occupied_thresh", occupied), ("free_thresh", free)):
        if not 0.0 <= value <= 1.0:
            raise MapError(f"{source}: {key}: must be between 0 and 1, got {value}")
    if free > occupied:
        raise MapError(f"{source}: free_thresh: must not exceed occupied_thresh ({free} > {occupied})")
    mode_value = items.get("mode", "trinary")
    mode = _unquote(mode_value, f"{source}: mode").lower() if isinstance(mode_value, str) else ""
    if mode not in MODES:
        raise MapError(f"{source}: mode: expected one of {', '.join(MODES)}, got {mode_value!r}")
    return MapYaml(
        image=image,
        resolution=resolution,
        origin=(origin[0], origin[1], origin[2]),
        negate=negate_text in ("1", "true"),
        occupied_thresh=occupied,
        free_thresh=free,
        mode=mode,
    )


# -- PGM -------------------------------------------------------------------------------------------


def read_pgm(path: str | Path) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
    """Read a binary (``P5``) or ASCII (``P2``) PGM, 8 or 16 bit, header comments allowed.

    Returns the pixels as stored (row 0 = the top row of the picture): uint8 when maxval < 256,
    uint16 otherwise. ``read_map`` scales them to 0-255 with the header's maxval (``to_8bit``).
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MapError(f"{p}: cannot read: {exc}") from exc
    image, _maxval = _parse_pgm(data, str(p))
    return image


def _parse_pgm(data: bytes, source: str) -> tuple[npt.NDArray[np.uint8] | npt.NDArray[np.uint16], int]:
    magic = data[:2]
    if magic not in (b"P5", b"P2"):
        if data[:8] == b"\x89PNG\r\n\x1a\n":
            raise MapError(f"{source}: PNG images are not supported; convert the map to PGM (P5)")
        raise MapError(f"{source}: not a PGM image (expected P5 or P2, found {magic!r})")
    pos = 2
    fields: list[int] = []
    while len(fields) < 3:
        # whitespace and comments between header fields
        while pos < len(data):
            ch = data[pos : pos + 1]
            if ch in (b" ", b"\t", b"\r", b"\n", b"\v", b"\f"):
                pos += 1
            elif ch == b"#":
                end = data.find(b"\n", pos)
                pos = len(data) if end < 0 else end + 1
            else:
                break
        start = pos
        while pos < len(data) and data[pos : pos + 1].isdigit():
            pos += 1
        if start == pos:
            what = ("width", "height", "maxval")[len(fields)]
            raise MapError(f"{source}: PGM header: expected the {what}, found {data[start : start + 10]!r}")
        fields.append(int(data[start:pos]))
    width, height, maxval = fields
    if width <= 0 or height <= 0:
        raise MapError(f"{source}: PGM header: width and height must be positive, got {width} x {height}")
    if not 0 < maxval < 65536:
        raise MapError(f"{source}: PGM header: maxval must be 1-65535, got {maxval}")
    wide = maxval > 255
    count = width * height
    if magic == b"P5":
        # exactly one whitespace character separates maxval from the pixels
        if pos >= len(data) or data[pos : pos + 1] not in (b" ", b"\t", b"\r", b"\n"):
            raise MapError(f"{source}: PGM header: expected one whitespace character after maxval")
        pos += 1
        size = count * (2 if wide else 1)
        if len(data) - pos < size:
            raise MapError(
                f"{source}: truncated: expected {size} bytes of pixels for {width} x {height}, found {len(data) - pos}"
            )
        if wide:  # 16-bit samples are big-endian
            top = int(np.frombuffer(data, dtype=">u2", count=count, offset=pos).max())
        else:
            top = int(np.frombuffer(data, dtype=np.uint8, count=count, offset=pos).max())
        if top > maxval:
            raise MapError(f"{source}: a pixel value ({top}) exceeds maxval {maxval}")
        if wide:
            wide_pixels = np.frombuffer(data, dtype=">u2", count=count, offset=pos).astype(np.uint16)
            return wide_pixels.reshape(height, width), maxval
        pixels = np.frombuffer(data, dtype=np.uint8, count=count, offset=pos).copy()
        return pixels.reshape(height, width), maxval
    text = re.sub(rb"#[^\n]*", b" ", data[pos:])
    tokens = text.split()
    if len(tokens) < count:
        raise MapError(
            f"{source}: truncated: expected {count} pixel values for {width} x {height}, found {len(tokens)}"
        )
    try:
        values = np.array([int(t) for t in tokens[:count]], dtype=np.int64)
    except ValueError:
        raise MapError(f"{source}: P2 pixels: expected whole numbers") from None
    if values.min() < 0 or values.max() > maxval:
        raise MapError(f"{source}: P2 pixels: values must be 0..{maxval}, found {values.min()}..{values.max()}")
    if wide:
        return values.astype(np.uint16).reshape(height, width), maxval
    return values.astype(np.uint8).reshape(height, width), maxval


def to_8bit(image: npt.NDArray[np.uint8] | npt.NDArray[np.uint16], maxval: int) -> npt.NDArray[np.uint8]:
    """Scale pixels to 0-255 as SDL_image does for maxval < 255 (``v * 255 // maxval``); 16-bit likewise."""
    if maxval == 255:
        return image.astype(np.uint8)
    return (image.astype(np.int64) * 255 // maxval).astype(np.uint8)


def write_pgm(path: str | Path, image: npt.ArrayLike, comment: str = "") -> Path:
    """Write an 8-bit binary (``P5``) PGM; ``image`` row 0 is the top row of the picture."""
    a = np.asarray(image)
    if a.ndim != 2 or a.size == 0:
        raise MapError(f"{path}: expected a non-empty 2-D image, got shape {a.shape}")
    if a.dtype.kind not in "iub" or a.min() < 0 or a.max() > 255:
        raise MapError(f"{path}: expected integer pixels 0-255")
    if "\n" in comment:
        raise MapError(f"{path}: the comment must be one line")
    header = "P5\n" + (f"# {comment}\n" if comment else "") + f"{a.shape[1]} {a.shape[0]}\n255\n"
    p = Path(path)
    p.write_bytes(header.encode("ascii") + np.ascontiguousarray(a, dtype=np.uint8).tobytes())
    return p


# -- image <-> grid --------------------------------------------------------------------------------


def grid_from_image(
    image: npt.ArrayLike,
    negate: bool = False,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.196,
    mode: str = "trinary",
) -> npt.NDArray[np.int8]:
    """map_server's image_loader on an 8-bit grey image (row 0 = top): the int8 grid, row 0 = bottom."""
    if mode not in MODES:
        raise MapError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
    a = np.asarray(image)
    if a.ndim != 2:
        raise MapError(f"expected a 2-D grey image, got shape {a.shape}")
    color = a.astype(np.float64)
    if negate:
        color = 255.0 - color
    if mode == "raw":
        # value = color_avg into an unsigned char, stored in the int8 grid (255 -> -1)
        values = color.astype(np.uint8).view(np.int8)
    else:
        occ = (255.0 - color) / 255.0
        values = np.full(a.shape, UNKNOWN, dtype=np.int8)
        if mode == "scale":
            span = occupied_thresh - free_thresh
            ratio = (occ - free_thresh) / span if span > 0 else np.zeros_like(occ)
            values = (1.0 + 98.0 * ratio).astype(np.int64).clip(-128, 127).astype(np.int8)
        values[occ < free_thresh] = FREE
        values[occ > occupied_thresh] = OCCUPIED
    return np.ascontiguousarray(values[::-1])


def image_from_grid(
    grid: npt.ArrayLike,
    threshold_free: int = SAVER_THRESHOLD_FREE,
    threshold_occupied: int = SAVER_THRESHOLD_OCCUPIED,
) -> npt.NDArray[np.uint8]:
    """map_saver's pixels for a grid (row 0 = bottom): 0 <= v <= free -> 254, v >= occ -> 0, else 205."""
    g = _check_grid(grid)
    image = np.full(g.shape, PGM_UNKNOWN, dtype=np.uint8)
    image[(g >= 0) & (g <= threshold_free)] = PGM_FREE
    image[g >= threshold_occupied] = PGM_OCCUPIED
    return np.ascontiguousarray(image[::-1])


def _check_grid(grid: npt.ArrayLike) -> npt.NDArray[np.int16]:
    g = np.asarray(grid)
    if g.ndim != 2 or g.size == 0:
        raise MapError(f"grid: expected a non-empty 2-D array, got shape {g.shape}")
    if g.dtype.kind not in "iu":
        raise MapError(f"grid: expected integer cells (-1 unknown, 0-100), got dtype {g.dtype}")
    if g.min() < -1 or g.max() > 100:
        raise MapError(f"grid: cells must be -1 (unknown) or 0-100, found {int(g.min())}..{int(g.max())}")
    return g.astype(np.int16)


# -- files -----------------------------------------------------------------------------------------


def read_map(yaml_path: str | Path) -> OccupancyMap:
    """Load a map_server map from its YAML file (and the image it names)."""
    p = Path(yaml_path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise MapError(f"{p}: cannot read: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise MapError(f"{p}: not a text (YAML) file: {exc}") from exc
    meta = parse_map_yaml(text, str(p), p.parent)
    if not meta.image.is_file():
        raise MapError(f"{p}: image: no such file {meta.image}")
    try:
        data = meta.image.read_bytes()
    except OSError as exc:
        raise MapError(f"{p}: image: cannot read {meta.image}: {exc}") from exc
    image, maxval = _parse_pgm(data, str(meta.image))
    grid = grid_from_image(to_8bit(image, maxval), meta.negate, meta.occupied_thresh, meta.free_thresh, meta.mode)
    return OccupancyMap(
        grid=grid,
        resolution=meta.resolution,
        origin=meta.origin,
        image=image,
        negate=meta.negate,
        occupied_thresh=meta.occupied_thresh,
        free_thresh=meta.free_thresh,
        mode=meta.mode,
        source=str(p),
    )


def _fmt(value: float) -> str:
    """``%f`` like map_saver, unless that would lose precision (then the shortest exact form)."""
    text = f"{value:f}"
    return text if float(text) == value else repr(float(value))


def write_map(
    grid: npt.ArrayLike,
    resolution: float,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    out: str | Path = ".",
    name: str = "map",
    *,
    threshold_free: int = SAVER_THRESHOLD_FREE,
    threshold_occupied: int = SAVER_THRESHOLD_OCCUPIED,
) -> Path:
    """Write ``<name>.pgm`` and ``<name>.yaml`` as map_saver does; returns the YAML's path.

    ``out`` is a folder (existing, or given with a trailing slash: then ``<out>/<name>.*``) or a base
    path such as ``maps/floor2`` (then ``maps/floor2.pgm`` and ``maps/floor2.yaml``; ``name`` unused).
    ``grid`` is (height, width) with row 0 = bottom, -1 unknown and 0-100 occupancy. The YAML names
    the image by its file name (map_saver writes the ``-f`` path as given), so the pair can move.
    """
    if not (isinstance(resolution, (int, float)) and math.isfinite(resolution) and resolution > 0):
        raise MapError(f"resolution: must be a finite number > 0, got {resolution!r}")
    o = [float(v) for v in origin]
    if len(o) == 2:
        o.append(0.0)
    if len(o) != 3 or not all(math.isfinite(v) for v in o):
        raise MapError(f"origin: expected finite [x, y] or [x, y, yaw], got {list(origin)!r}")
    if not name or "/" in name:
        raise MapError(f"name: expected a plain file name, got {name!r}")
    out_text = str(out)
    target = Path(out)
    if target.is_dir() or out_text.endswith(("/", "\\")):
        base = target / name
    else:
        base = target.with_suffix("") if target.suffix in (".yaml", ".yml", ".pgm") else target
    base.parent.mkdir(parents=True, exist_ok=True)
    image = image_from_grid(grid, threshold_free, threshold_occupied)
    pgm = base.with_name(base.name + ".pgm")
    yaml = base.with_name(base.name + ".yaml")
    write_pgm(pgm, image, comment=f"CREATOR: fleetlink mapserver.py {resolution:.3f} m/pix")
    yaml.write_text(
        f"image: {pgm.name}\n"
        f"resolution: {_fmt(resolution)}\n"
        f"origin: [{_fmt(o[0])}, {_fmt(o[1])}, {_fmt(o[2])}]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
        "\n",
        encoding="ascii",
    )
    return yaml


# -- walls from a grid -----------------------------------------------------------------------------


def _runs(mask: npt.NDArray[np.bool_]) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Runs of True along each row: (row, first, end) with ``end`` exclusive."""
    padded = np.zeros((mask.shape[0], mask.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = mask
    d = np.diff(padded, axis=1)
    rows, first = np.nonzero(d == 1)
    _rows_end, end = np.nonzero(d == -1)
    return rows, first, end


def _to_world(origin: Sequence[float], resolution: float, u: float, v: float) -> tuple[float, float]:
    ox, oy, yaw = origin
    c, s = math.cos(yaw), math.sin(yaw)
    return ox + resolution * (c * u - s * v), oy + resolution * (s * u + c * v)


def boundary_segments(
    blocked: npt.ArrayLike, resolution: float, origin: Sequence[float] = (0.0, 0.0, 0.0)
) -> npt.NDArray[np.float64]:
    """Wall segments (N, 4: x1, y1, x2, y2 in metres) along every edge between a blocked and an open cell.

    ``blocked`` is (height, width), row 0 = bottom. Outside the grid counts as blocked, so open
    cells on the border get a wall and the map is closed. Collinear edges are merged into one
    segment (run-length along rows for horizontal edges, along columns for vertical ones), so an
    axis-aligned wall costs a few segments whatever its length; a diagonal wall costs two per step.
    """
    b = np.asarray(blocked, dtype=bool)
    if b.ndim != 2:
        raise MapError(f"blocked: expected a 2-D array, got shape {b.shape}")
    h, w = b.shape
    p = np.ones((h + 2, w + 2), dtype=bool)
    p[1:-1, 1:-1] = b
    horizontal = p[1:, 1:-1] != p[:-1, 1:-1]  # (h + 1, w): edge k lies at v = k
    vertical = p[1:-1, 1:] != p[1:-1, :-1]  # (h, w + 1): edge k lies at u = k
    hk, hu0, hu1 = _runs(horizontal)
    vk, vv0, vv1 = _runs(vertical.T)
    u1 = np.concatenate([hu0, vk]).astype(np.float64)
    v1 = np.concatenate([hk, vv0]).astype(np.float64)
    u2 = np.concatenate([hu1, vk]).astype(np.float64)
    v2 = np.concatenate([hk, vv1]).astype(np.float64)
    ox, oy, yaw = (float(v) for v in origin) if len(origin) == 3 else (float(origin[0]), float(origin[1]), 0.0)
    c, s = math.cos(yaw) * resolution, math.sin(yaw) * resolution
    out = np.empty((u1.size, 4), dtype=np.float64)
    out[:, 0] = ox + c * u1 - s * v1
    out[:, 1] = oy + s * u1 + c * v1
    out[:, 2] = ox + c * u2 - s * v2
    out[:, 3] = oy + s * u2 + c * v2
    return out
