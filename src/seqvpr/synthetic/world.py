"""A procedurally rendered synthetic city: camera images along routes through a generated 2-D street grid.

The project's embedded data for ``seqvpr demo`` and a test fixture, not a benchmark. A world is a grid of streets
(two lanes each way, sidewalks, markings, street lamps, trees) lined with buildings whose facades come from a set of
procedural templates. Two closed routes (train and test) drive different streets of it, far apart; each starts with
a lap of one block and passes its start again (a loop), and a few street stretches on each route carry identical
buildings (perceptual aliasing). A drive renders a route under one of the ``CONDITIONS``, with a lateral offset
(another lane), a varying speed with full stops, and per-frame sensor noise.

The renderer is a 2.5-D column raycaster: numpy picks the walls and camera-facing billboards (trees, lamps) in
view, and numba kernels intersect every image column's ray with them, draw the nearest few hits per column front to
back as vertical strips textured from a template atlas, project the floor for the road (markings, lamp light,
headlights), look the sky up in a panorama, and add fog, glow, exposure jitter and sensor noise. The kernels run on
one thread, so everything is deterministic for a seed: the same seed and parameters give byte-identical image files.
Headings are compass bearings (degrees clockwise from north); positions are metres (easting, northing).
"""

from __future__ import annotations

import csv
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit
from PIL import Image

from seqvpr.io import atomic_folder
from seqvpr.synthetic import CONDITIONS

CAMERA_HEIGHT = 1.5  # metres above the road
HFOV_DEG = 80.0  # horizontal field of view of the pinhole camera
HORIZON = 0.48  # horizon row as a fraction of the image height (camera pitched slightly down)
ROAD_HALF = 6.6  # kerb distance from the street centre line: two 3.2 m lanes each way plus gutter
LANE = 3.2  # lane width
DRIVE_LANE = 4.8  # the route's lane: centre of the outer right lane, metres right of the centre line
SETBACK = 10.0  # facade line distance from the centre line
CORNER = 18.0  # east/west block sides keep this clear of the corners (where north/south buildings stand)
FAR = 260.0  # nothing beyond this distance is raycast
NEAR = 0.3
LAYERS = 4  # nearest hits drawn per column (tree in front of lamp in front of facade in front of a taller one)
PX_PER_M = 10  # facade texture resolution
FACADE_W, FACADE_H = 200, 310  # facade template size in texels (20 m x 31 m)
TREE_W, TREE_H = 96, 144
LAMP_W, LAMP_H = 16, 80
N_FACADES, N_SIDEWALLS, N_TREES = 48, 8, 8
LAMP_SPACING = 28.0
LAMP_POOL = 3.5  # metres: radius of a lamp's pool of light on the ground
LIGHT_RES = 0.5  # metres per cell of the lamp light map
SKY_STEP = 0.005  # rows of the sky panorama: steps of the elevation's tangent
_TABLE_MARGIN = 200.0  # the nearest-street lookup tables reach this far beyond the outer streets
_LIGHT_MARGIN = 40.0  # the light map reaches this far beyond the outer streets
MOTIF_LENGTH = 50.0  # metres of identical buildings at the start of an aliased street stretch
ROUTE_RADIUS = 9.0  # corner fillet radius of the routes

# The route as grid nodes (i, j), cyclic: a clockwise lap of one block, past the start again, then a long circuit
# back to the start. Route edges k (from node k to node k + 1) in _MOTIF_EDGES start with identical buildings.
_ROUTE_NODES = (
    (1, 2), (2, 2), (2, 1), (1, 1), (1, 2), (2, 2), (3, 2), (4, 2), (5, 2), (5, 3), (5, 4), (6, 4), (6, 5),
    (6, 6), (6, 7), (5, 7), (4, 7), (4, 8), (3, 8), (2, 8), (1, 8), (1, 7), (1, 6), (1, 5), (0, 5), (0, 4),
    (0, 3), (0, 2),
)
_MOTIF_EDGES = (1, 3, 7, 9)
ROUTE_LEAD_IN = 30.0  # metres of the closing edge driven before the first node (where the lap starts)
_ROUTE_COLUMNS = {"train": (1, True), "test": (10, False)}  # first grid column and mirroring of each route
_N_XLINES, _N_YLINES = 18, 10


@dataclass(frozen=True)
class Drive:
    """How one traversal drives a route: condition, lateral offset, speed profile, frame rate, seed."""

    condition: str = "day"
    lateral_offset: float = 0.0  # metres, + = left
    mean_speed: float = 8.0  # m/s
    speed_variation: float = 0.0  # 0 = constant speed; 0.4 = +-40 %
    stops: int = 0  # number of full stops (each a few seconds)
    fps: float = 4.0
    seed: int = 0  # noise of this drive (speed profile, rain streaks, sensor noise)

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise ValueError(f"seed must be non-negative, got {self.seed}")
        if self.condition not in CONDITIONS:
            raise ValueError(f"condition {self.condition!r} is not known (choose from: {', '.join(CONDITIONS)})")
        if self.mean_speed <= 0 or self.fps <= 0:
            raise ValueError("mean_speed and fps must be positive")
        if not 0.0 <= self.speed_variation < 1.0 or self.stops < 0:
            raise ValueError("speed_variation must be in [0, 1) and stops non-negative")


@dataclass(frozen=True)
class Poses:
    """Camera poses of a traversal: positions [N, 2] metres, compass headings [N] degrees, timestamps [N] s."""

    positions: np.ndarray
    headings: np.ndarray
    timestamps: np.ndarray
    arc: np.ndarray  # distance driven along the route (metres), before any wrap-around


@dataclass(frozen=True)
class Look:
    """Lighting and weather of one condition."""

    ambient: tuple[float, float, float]
    sun: float  # how much wall orientation to the sun matters
    zenith: tuple[float, float, float]
    horizon: tuple[float, float, float]
    clouds: float
    cloud_color: tuple[float, float, float]
    fog: tuple[float, float, float]
    visibility: float  # metres for fog to take 63 % of a colour
    sky_fog: float  # how much the fog colour covers the sky
    lamps: float  # street lamps and lamp heads
    windows: float  # lit windows and shop signs
    headlights: float
    noise: float  # sensor noise (standard deviation, 0..1 scale)
    snow: bool = False
    rain: bool = False
    dusk_glow: float = 0.0


LOOKS = {
    "day": Look((1.0, 1.0, 0.98), 0.45, (0.33, 0.52, 0.82), (0.74, 0.82, 0.92), 0.55, (0.95, 0.95, 0.96),
                (0.78, 0.83, 0.9), 700.0, 0.0, 0.0, 0.0, 0.0, 0.008),
    "dusk": Look((0.5, 0.42, 0.42), 0.25, (0.16, 0.18, 0.38), (0.95, 0.55, 0.35), 0.4, (0.55, 0.35, 0.35),
                 (0.55, 0.42, 0.42), 500.0, 0.0, 0.55, 0.55, 0.35, 0.014, dusk_glow=0.6),
    "night": Look((0.2, 0.2, 0.24), 0.0, (0.03, 0.035, 0.07), (0.15, 0.12, 0.12), 0.25, (0.15, 0.12, 0.12),
                  (0.05, 0.05, 0.06), 400.0, 0.0, 1.0, 1.0, 0.4, 0.025),
    "winter": Look((0.97, 0.99, 1.04), 0.25, (0.6, 0.66, 0.75), (0.86, 0.88, 0.91), 0.4, (0.9, 0.9, 0.92),
                   (0.85, 0.87, 0.9), 350.0, 0.0, 0.0, 0.0, 0.0, 0.008, snow=True),
    "fog": Look((0.85, 0.86, 0.88), 0.05, (0.74, 0.75, 0.77), (0.76, 0.77, 0.79), 0.0, (0.75, 0.76, 0.78),
                (0.75, 0.76, 0.78), 38.0, 1.0, 0.0, 0.0, 0.0, 0.012),
    "rain": Look((0.5, 0.52, 0.56), 0.05, (0.4, 0.42, 0.46), (0.55, 0.57, 0.6), 0.3, (0.45, 0.46, 0.5),
                 (0.5, 0.52, 0.55), 110.0, 0.6, 0.0, 0.2, 0.25, 0.018, rain=True),
}


@dataclass
class Panels:
    """Vertical textured quads standing on the ground: walls and billboards."""

    p0: np.ndarray  # [P, 2] metres
    p1: np.ndarray  # [P, 2]
    top: np.ndarray  # [P] metres
    template: np.ndarray  # [P] atlas template index
    u0: np.ndarray  # [P] texture offset along the panel (metres)
    tint: np.ndarray  # [P, 3]
    sunlit: np.ndarray  # [P] 0..1, how much the wall faces the sun
    roofline: np.ndarray  # [P] bool: draw a coping (snow in winter) along the top


@dataclass
class Sprites:
    """Camera-facing billboards: trees and street lamps."""

    centre: np.ndarray  # [T, 2]
    width: np.ndarray  # [T]
    height: np.ndarray  # [T]
    template: np.ndarray  # [T]


@dataclass
class Atlas:
    """All templates side by side in one texel array: RGB albedo, alpha, emission (uint8 [cols, rows, 5]).

    Stored column-major (a texture column is contiguous) because the renderer draws images column by column.
    """

    texels: np.ndarray
    col0: np.ndarray  # [templates] first column
    width: np.ndarray  # [templates] texels
    height: np.ndarray  # [templates] texels


@dataclass
class World:
    """A generated city: street grid lines, wall panels, trees and lamps, textures and lighting (lazily built)."""

    seed: int
    xs: np.ndarray  # x of the north-south street centre lines (sorted)
    ys: np.ndarray  # y of the east-west street centre lines (sorted)
    panels: Panels
    sprites: Sprites
    lamps: np.ndarray  # [L, 2] lamp positions (also sprites)
    # per route, the aliased stretches: where on the street centre line the shared buildings begin, and the
    # direction of travel along which they are laid out (both sides of the street look the same for MOTIF_LENGTH)
    motifs: dict[str, list[tuple[np.ndarray, np.ndarray]]]
    template_sizes: list[tuple[int, int]]
    template_kinds: list[tuple[str, int]]
    _atlases: dict[bool, Atlas] = field(default_factory=dict, repr=False)
    _light: np.ndarray | None = field(default=None, repr=False)
    _ground_noise: np.ndarray | None = field(default=None, repr=False)
    _clouds: np.ndarray | None = field(default=None, repr=False)
    _tables: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    _skies: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def atlas(self, snow: bool) -> Atlas:
        """The texture atlas (summer or snowy variant), painted on first use."""
        if snow not in self._atlases:
            self._atlases[snow] = _paint_atlas(self, snow)
        return self._atlases[snow]

    def light_map(self) -> np.ndarray:
        """Street-lamp light on the ground (float32 raster, LIGHT_RES metres per cell), splatted on first use."""
        if self._light is None:
            self._light = _splat_lamps(self)
        return self._light

    def ground_noise(self) -> np.ndarray:
        """A tileable 256x256 texture of road grain (two octaves), made on first use."""
        if self._ground_noise is None:
            rng = np.random.default_rng([self.seed, 7])
            self._ground_noise = np.stack([_periodic_noise(rng, 256, 256, s) for s in (1.5, 12.0)])
        return self._ground_noise

    def line_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """Lookup tables of the nearest north-south and east-west street line per metre, made on first use."""
        if self._tables is None:
            self._tables = (_line_table(self.xs), _line_table(self.ys))
        return self._tables

    def sky(self, condition: str) -> np.ndarray:
        """The sky panorama of a condition [tan(elevation) / SKY_STEP, azimuth in 720 steps, RGB], made on first use."""
        if condition not in self._skies:
            self._skies[condition] = _sky_panorama(self.clouds(), _look_vector(LOOKS[condition]))
        return self._skies[condition]

    def clouds(self) -> np.ndarray:
        """A cloud panorama [rows = elevation 0..90 deg, cols = azimuth 0..360 deg] in [0, 1], made on first use."""
        if self._clouds is None:
            rng = np.random.default_rng([self.seed, 8])
            noise = 0.65 * _periodic_noise(rng, 128, 720, 18.0) + 0.35 * _periodic_noise(rng, 128, 720, 5.0)
            self._clouds = (0.5 + 0.5 * noise / (np.abs(noise).max() + 1e-6)).astype(np.float32)
        return self._clouds


# ----------------------------------------------------------------------------------------------- noise


def _periodic_noise(rng: np.random.Generator, h: int, w: int, scale: float) -> np.ndarray:
    """Smooth noise that tiles in both directions (white noise low-passed over ``scale`` texels), unit std."""
    white = rng.standard_normal((h, w))
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    spectrum = np.fft.rfft2(white) * np.exp(-((fy**2 + fx**2) * (np.pi * scale) ** 2))
    field_ = np.fft.irfft2(spectrum, s=(h, w))
    return (field_ / (field_.std() + 1e-12)).astype(np.float32)


# ----------------------------------------------------------------------------------------------- world


@functools.lru_cache(maxsize=2)
def build_world(seed: int = 0) -> World:
    """The world of a seed: a street grid with buildings on every block, trees, lamps and two routes' aliasing.

    Cached (the same seed gives the same object), so its lazily painted textures are made once per process.
    """
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    rng = np.random.default_rng([seed, 0])
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(85.0, 125.0, _N_XLINES - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(85.0, 125.0, _N_YLINES - 1))])
    motif_sides, motifs = _motif_sides(xs, ys)
    layouts = [_facade_layout(_facade_rng(seed, t)) for t in range(N_FACADES)]
    walls: list[tuple] = []
    trees: list[tuple] = []
    for bi in range(_N_XLINES - 1):
        for bj in range(_N_YLINES - 1):
            for side in range(4):
                _fill_block_side(seed, xs, ys, bi, bj, side, motif_sides, layouts, walls, trees)
    lamps = _lamp_positions(xs, ys)
    panels = _panels_from_walls(walls)
    n_tpl = N_FACADES + N_SIDEWALLS
    centre = np.array([t[0] for t in trees] + [tuple(p) for p in lamps], dtype=np.float64).reshape(-1, 2)
    sprites = Sprites(
        centre=centre,
        width=np.array([t[1] for t in trees] + [LAMP_W / PX_PER_M] * len(lamps), dtype=np.float64),
        height=np.array([t[2] for t in trees] + [LAMP_H / PX_PER_M] * len(lamps), dtype=np.float64),
        template=np.array([n_tpl + t[3] for t in trees] + [n_tpl + N_TREES] * len(lamps), dtype=np.int64),
    )
    sizes = [(FACADE_W, FACADE_H)] * n_tpl + [(TREE_W, TREE_H)] * N_TREES + [(LAMP_W, LAMP_H)]
    kinds = ([("facade", i) for i in range(N_FACADES)] + [("side", i) for i in range(N_SIDEWALLS)]
             + [("tree", i) for i in range(N_TREES)] + [("lamp", 0)])
    return World(seed, xs, ys, panels, sprites, lamps, motifs, sizes, kinds)


def _route_edges(which: str) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """The route's edges as pairs of global grid nodes (i, j), in driving order, cyclic."""
    first, mirror = _ROUTE_COLUMNS[which]
    nodes = [(first + (6 - i if mirror else i), j) for i, j in _ROUTE_NODES]
    return [(nodes[k], nodes[(k + 1) % len(nodes)]) for k in range(len(nodes))]


def _motif_sides(xs: np.ndarray, ys: np.ndarray) -> tuple[dict, dict]:
    """Which block sides start with a shared motif (and in which direction), and where the motifs are."""
    sides: dict[tuple[int, int, int], tuple[int, int, bool]] = {}
    places: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for r, which in enumerate(_ROUTE_COLUMNS):
        edges = _route_edges(which)
        places[which] = []
        for k in _MOTIF_EDGES:
            (i0, j0), (i1, j1) = edges[k]
            a = np.array([xs[i0], ys[j0]])
            b = np.array([xs[i1], ys[j1]])
            direction = (b - a) / np.linalg.norm(b - a)
            lead = SETBACK if j0 == j1 else SETBACK + CORNER  # where the block sides along the street begin
            places[which].append((a + lead * direction, direction))
            forward = (i1 > i0) or (j1 > j0)
            if j0 == j1:  # east-west street: blocks south (north side of block) and north (south side)
                bi = min(i0, i1)
                sides[(bi, j0 - 1, 1)] = (r, forward, i1 < i0)  # north side of the block below
                sides[(bi, j0, 0)] = (r, forward, i1 > i0)  # south side of the block above
            else:
                bj = min(j0, j1)
                sides[(i0 - 1, bj, 3)] = (r, forward, j1 > j0)  # east side of the block to the west
                sides[(i0, bj, 2)] = (r, forward, j1 < j0)  # west side of the block to the east
    return sides, places


def _block_side_frame(xs, ys, bi, bj, side) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Start point, along direction, inward normal and usable length of one side of a block (S, N, W, E)."""
    x0, x1 = xs[bi] + SETBACK, xs[bi + 1] - SETBACK
    y0, y1 = ys[bj] + SETBACK, ys[bj + 1] - SETBACK
    if side == 0:
        return np.array([x0, y0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), x1 - x0
    if side == 1:
        return np.array([x0, y1]), np.array([1.0, 0.0]), np.array([0.0, -1.0]), x1 - x0
    if side == 2:
        return np.array([x0, y0 + CORNER]), np.array([0.0, 1.0]), np.array([1.0, 0.0]), y1 - y0 - 2 * CORNER
    return np.array([x1, y0 + CORNER]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), y1 - y0 - 2 * CORNER


def _fill_block_side(seed, xs, ys, bi, bj, side, motif_sides, layouts, walls, trees) -> None:
    """Line one block side with buildings, gaps and street trees; motif sides start with shared content."""
    start, along, inward, length = _block_side_frame(xs, ys, bi, bj, side)
    own = np.random.default_rng([seed, 1, bi, bj, side])
    shared = None
    motif = motif_sides.get((bi, bj, side))
    if motif is not None:
        route_id, forward, is_left = motif
        if not forward:  # lay the motif out from the end a driver enters
            start, along = start + along * length, -along
        shared = np.random.default_rng([seed, 2, route_id, int(is_left)])
    a = 0.0
    street = -inward * (SETBACK - ROAD_HALF - 1.4)  # tree line on the sidewalk, 1.4 m from the kerb
    tree_lined = own.random() < 0.55
    if shared is not None:
        tree_lined = shared.random() < 0.8
    next_tree = 4.0
    while a < length - 4.0:
        rng = shared if shared is not None and a < MOTIF_LENGTH else own
        if tree_lined:
            while next_tree < min(a + 30.0, length - 2.0):
                trees.append(_tree(rng, start + along * next_tree + street))
                next_tree += rng.uniform(8.0, 13.0)
        if rng.random() < 0.1:  # a gap: a yard or parking lot, sometimes with trees
            gap = rng.uniform(4.0, 12.0)
            for _ in range(rng.integers(0, 3)):
                at = start + along * (a + rng.uniform(1.0, gap - 1.0))
                trees.append(_tree(rng, at + inward * rng.uniform(3, 12)))
            a += gap
            continue
        width = min(rng.uniform(9.0, 24.0), length - a)
        depth = rng.uniform(10.0, 17.0)
        template = int(rng.integers(N_FACADES))
        floors = int(rng.integers(2, 9))
        side_template = N_FACADES + int(rng.integers(N_SIDEWALLS))
        bays, ground, storey = layouts[template]
        u0 = (FACADE_W / PX_PER_M / bays) * int(rng.integers(bays))
        tint = np.exp(rng.normal(0.0, 0.09, 3))
        height = min(ground + (floors - 1) * storey + rng.uniform(0.5, 1.2), FACADE_H / PX_PER_M - 0.2)
        if width >= 4.0:
            walls.append((start + along * a, along, inward, width, depth, height, template, side_template, u0, tint))
        a += width


def _tree(rng: np.random.Generator, at: np.ndarray) -> tuple:
    """One tree: position, crown width, height and template, drawn from ``rng``."""
    height = rng.uniform(6.0, 10.0)
    return (tuple(at), height * rng.uniform(0.55, 0.75), height, int(rng.integers(N_TREES)))


def _lamp_positions(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Street lamps along every street edge, both sides staggered, clear of the junctions."""
    lamps = []
    lateral = ROAD_HALF + 0.5
    for horizontal, lines, cross in ((False, xs, ys), (True, ys, xs)):
        for line in lines:
            for c0, c1 in zip(cross[:-1], cross[1:]):
                for side, phase in ((-1.0, 0.0), (1.0, LAMP_SPACING / 2)):
                    along = np.arange(c0 + SETBACK + 4.0 + phase, c1 - SETBACK - 2.0, LAMP_SPACING)
                    for s in along:
                        lamps.append((s, line + side * lateral) if horizontal else (line + side * lateral, s))
    return np.array(lamps, dtype=np.float64)


def _panels_from_walls(walls: list[tuple]) -> Panels:
    """Four wall panels per building footprint: the street facade and three side walls, outward-facing."""
    p0, p1, top, tpl, u0, tint, roof = [], [], [], [], [], [], []
    for start, along, inward, width, depth, height, template, side_template, offset, color in walls:
        a, b = start, start + along * width
        c, d = b + inward * depth, a + inward * depth
        # outward normal of p0->p1 is (dy, -dx) for counter-clockwise corners; order them so
        ring = [a, b, c, d]
        area = sum(ring[k][0] * ring[(k + 1) % 4][1] - ring[(k + 1) % 4][0] * ring[k][1] for k in range(4))
        facade_first = area > 0
        corners = ring if facade_first else [b, a, d, c]
        for k in range(4):
            q0, q1 = corners[k], corners[(k + 1) % 4]
            is_front = k == 0
            p0.append(q0)
            p1.append(q1)
            top.append(height)
            tpl.append(template if is_front else side_template)
            u0.append(offset if is_front else 0.0)
            tint.append(color)
            roof.append(True)
    p0a, p1a = np.array(p0), np.array(p1)
    edge = p1a - p0a
    normal = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / np.linalg.norm(edge, axis=1, keepdims=True)
    sun = np.array([math.sin(math.radians(150.0)), math.cos(math.radians(150.0))])  # sun in the south-south-east
    return Panels(
        p0=p0a, p1=p1a, top=np.array(top), template=np.array(tpl, dtype=np.int64), u0=np.array(u0),
        tint=np.array(tint, dtype=np.float32), sunlit=np.clip(normal @ sun, 0.0, 1.0).astype(np.float32),
        roofline=np.array(roof, dtype=bool),
    )


# ----------------------------------------------------------------------------------------------- textures


def _facade_rng(seed: int, template: int) -> np.random.Generator:
    """The random stream that paints one facade template (the same for the summer and snowy variants)."""
    return np.random.default_rng([seed, 3, template])


def _facade_layout(rng: np.random.Generator) -> tuple[int, float, float]:
    """The first draws of a facade template: window bays across its 20 m, ground-floor and storey heights (m)."""
    return int(rng.integers(4, 9)), float(rng.uniform(3.6, 4.6)), float(rng.uniform(2.9, 3.5))


_WALL_COLORS = np.array([
    (0.56, 0.30, 0.22), (0.66, 0.38, 0.27), (0.78, 0.70, 0.55), (0.88, 0.84, 0.74), (0.62, 0.62, 0.60),
    (0.38, 0.38, 0.40), (0.90, 0.89, 0.86), (0.80, 0.60, 0.32), (0.58, 0.68, 0.76), (0.62, 0.72, 0.58),
    (0.47, 0.35, 0.27), (0.82, 0.66, 0.60), (0.70, 0.52, 0.42), (0.52, 0.50, 0.46),
], dtype=np.float32)
_SIGN_COLORS = np.array([
    (0.8, 0.1, 0.1), (0.1, 0.3, 0.75), (0.1, 0.55, 0.2), (0.95, 0.75, 0.1), (0.1, 0.1, 0.1), (0.95, 0.95, 0.95),
    (0.6, 0.15, 0.55), (0.95, 0.45, 0.05), (0.05, 0.55, 0.6),
], dtype=np.float32)
_SNOW = np.array([0.93, 0.94, 0.97], dtype=np.float32)


def _paint_wall(rng: np.random.Generator) -> np.ndarray:
    """A facade's bare wall (float [FACADE_H, FACADE_W, 3]): one colour with grain, brick courses in a third."""
    wall = _WALL_COLORS[rng.integers(len(_WALL_COLORS))] * rng.uniform(0.85, 1.1, 3).astype(np.float32)
    grain = _periodic_noise(rng, FACADE_H, FACADE_W, 1.0) * 0.05 + _periodic_noise(rng, FACADE_H, FACADE_W, 12.0) * 0.06
    rgb = np.clip(wall[None, None, :] * (1.0 + grain[..., None]), 0, 1)
    if rng.random() < 0.35:  # brick courses
        rgb = rgb * np.where((np.arange(FACADE_H) % 3 == 0)[:, None, None], 0.85, 1.0)
    return rgb


def _paint_facade(rng: np.random.Generator, snow: bool) -> np.ndarray:
    """One street facade (uint8 [FACADE_H, FACADE_W, 5], row 0 at the ground): storeys of windows over a shop
    or residential ground floor, with per-window curtains and lights; snow on sills and ledges when asked."""
    n_bays, ground, storey = _facade_layout(rng)
    bay = FACADE_W / PX_PER_M / n_bays
    z = ((np.arange(FACADE_H) + 0.5) / PX_PER_M)[:, None]
    u = ((np.arange(FACADE_W) + 0.5) / PX_PER_M)[None, :]
    rgb = _paint_wall(rng)
    emission = np.zeros((FACADE_H, FACADE_W), np.float32)
    width = bay * rng.uniform(0.38, 0.62)
    win_h = storey * rng.uniform(0.42, 0.6)
    sill = rng.uniform(0.7, 0.95)
    frame_color = np.array((0.92, 0.92, 0.9) if rng.random() < 0.6 else (0.2, 0.18, 0.16), np.float32)
    mullion = rng.random() < 0.5
    cornices = rng.random() < 0.5
    pilasters = rng.random() < 0.3
    lit_share = rng.uniform(0.25, 0.55)
    n_floors = int((FACADE_H / PX_PER_M - ground) / storey) + 2
    curtains = rng.uniform(0.15, 0.8, (n_floors, n_bays, 3)).astype(np.float32)
    curtained = rng.random((n_floors, n_bays)) < 0.45
    lit = rng.random((n_floors, n_bays)) < lit_share
    glow = rng.uniform(0.55, 1.0, (n_floors, n_bays)).astype(np.float32)
    floor = np.clip(((z - ground) // storey).astype(np.int64) + 1, 0, n_floors - 1) * (z >= ground)
    zf = np.where(z >= ground, (z - ground) % storey, z)
    bay_i = np.minimum((u // bay).astype(np.int64), n_bays - 1)
    uf = u % bay - bay / 2
    upper = z >= ground
    if pilasters:
        rgb = np.where((upper & (np.abs(np.abs(uf) - bay / 2) < 0.18))[..., None], rgb * 1.12, rgb)
    if cornices:
        band = upper & (zf < 0.25)
        rgb = np.where(band[..., None], rgb * 0.78, rgb)
    in_win = upper & (np.abs(uf) < width / 2) & (zf > sill) & (zf < sill + win_h)
    in_frame = upper & (np.abs(uf) < width / 2 + 0.1) & (zf > sill - 0.1) & (zf < sill + win_h + 0.1) & ~in_win
    if mullion:
        in_frame |= in_win & (np.abs(uf) < 0.05)
        in_win &= ~(np.abs(uf) < 0.05)
    sky_reflection = np.array((0.06, 0.084, 0.12), np.float32)  # brighter towards the top of each window
    glass = np.array((0.1, 0.12, 0.16), np.float32) + (zf / storey)[..., None] * sky_reflection
    pane = np.where(curtained[floor, bay_i][..., None], curtains[floor, bay_i] * 0.8, glass)
    rgb = np.where(in_frame[..., None], frame_color, rgb)
    rgb = np.where(in_win[..., None], pane, rgb)
    emission = np.where(in_win & lit[floor, bay_i], glow[floor, bay_i], emission)
    if snow:
        ledge = upper & (np.abs(uf) < width / 2 + 0.15) & (zf > sill - 0.2) & (zf < sill - 0.02)
        rgb = np.where(ledge[..., None], _SNOW, rgb)
    rgb, emission = _paint_ground_floor(rng, rgb, emission, z, u, ground, bay, n_bays, snow)
    return _pack(rgb, np.ones_like(emission), emission)


def _paint_ground_floor(rng, rgb, emission, z, u, ground, bay, n_bays, snow) -> tuple[np.ndarray, np.ndarray]:
    """A shop front (display windows, a lit sign with letters, maybe an awning) or a residential ground floor."""
    low = z < ground
    uf = u % bay - bay / 2
    bay_i = np.minimum((u // bay).astype(np.int64), n_bays - 1)
    door_bay = int(rng.integers(n_bays))
    if rng.random() < 0.6:
        sign = _SIGN_COLORS[rng.integers(len(_SIGN_COLORS))]
        ink = np.array((0.97, 0.97, 0.95) if sign.mean() < 0.6 else (0.08, 0.08, 0.1), np.float32)
        top_w = ground - 1.0
        display = low & (z > 0.35) & (z < top_w) & (np.abs(uf) < bay / 2 - 0.3)
        shop_glass = np.array((0.16, 0.18, 0.2), np.float32) + 0.25 * rng.random((n_bays, 3)).astype(np.float32)
        rgb = np.where(display[..., None], shop_glass[bay_i], rgb)
        door = display & (bay_i == door_bay) & (np.abs(uf) < 0.6)
        rgb = np.where(door[..., None], np.array((0.12, 0.1, 0.08), np.float32), rgb)
        lit_shop = rng.random() < 0.75
        emission = np.where(display & lit_shop & ~door, rng.uniform(0.6, 0.95), emission)
        band = low & (z >= top_w + 0.15) & (z < ground - 0.15)
        letters = rng.random((4, 60)) < 0.55
        ci = np.clip(((z - top_w - 0.15) / (ground - 0.3 - top_w) * 4).astype(np.int64), 0, 3)
        cj = np.minimum((u / 0.33).astype(np.int64), 59)
        sign_span = (u > rng.uniform(0.5, 4.0)) & (u < rng.uniform(12.0, 19.5))
        glyph = band & sign_span & letters[ci, cj] & (ci > 0) & (ci < 3)
        rgb = np.where(band[..., None], sign, rgb)
        rgb = np.where(glyph[..., None], ink, rgb)
        emission = np.where(band & sign_span, 0.8, emission)
        if rng.random() < 0.4:
            stripes = (u // 0.5 % 2 == 0)
            awning = low & (z > top_w - 0.55) & (z < top_w) & (bay_i != door_bay)
            color = _SIGN_COLORS[rng.integers(len(_SIGN_COLORS))]
            rgb = np.where((awning & stripes)[..., None], color, np.where(awning[..., None], 0.92, rgb))
            emission = np.where(awning, 0.0, emission)
        if snow:
            rgb = np.where((low & (z >= ground - 0.15) & (z < ground))[..., None], _SNOW, rgb)
    else:
        win = low & (np.abs(uf) < bay * 0.25) & (z > 1.1) & (z < ground - 0.8) & (bay_i != door_bay)
        rgb = np.where(win[..., None], np.array((0.12, 0.13, 0.16), np.float32), rgb)
        emission = np.where(win & (rng.random((1, n_bays)) < 0.4)[0][bay_i], 0.7, emission)
        door = low & (bay_i == door_bay) & (np.abs(uf) < 0.65) & (z < 2.4)
        rgb = np.where(door[..., None], np.array((0.3, 0.18, 0.1), np.float32), rgb)
        plinth = low & (z < 0.5)
        rgb = np.where(plinth[..., None], rgb * 0.7, rgb)
    return rgb, emission


def _paint_side_wall(rng: np.random.Generator, snow: bool) -> np.ndarray:
    """A plain side or back wall: one colour, grain, sparse small windows."""
    z = ((np.arange(FACADE_H) + 0.5) / PX_PER_M)[:, None]
    u = ((np.arange(FACADE_W) + 0.5) / PX_PER_M)[None, :]
    wall = _WALL_COLORS[rng.integers(len(_WALL_COLORS))] * np.float32(rng.uniform(0.75, 0.95))
    grain = _periodic_noise(rng, FACADE_H, FACADE_W, 2.0) * 0.05 + _periodic_noise(rng, FACADE_H, FACADE_W, 20.0) * 0.08
    rgb = np.clip(wall[None, None, :] * (1.0 + grain[..., None]), 0, 1)
    cells = rng.random((12, 8)) < 0.18
    lit = rng.random((12, 8)) < 0.35
    ci = np.minimum((z // 3.0).astype(np.int64), 11)
    cj = np.minimum((u // 2.5).astype(np.int64), 7)
    win = cells[ci, cj] & (np.abs(u % 2.5 - 1.25) < 0.4) & (z % 3.0 > 1.0) & (z % 3.0 < 2.2) & (z > 3.0)
    rgb = np.where(win[..., None], np.array((0.12, 0.13, 0.16), np.float32), rgb)
    emission = np.where(win & lit[ci, cj], 0.7, 0.0).astype(np.float32)
    return _pack(rgb, np.ones_like(emission), emission)


def _paint_tree(rng: np.random.Generator, bare: bool) -> np.ndarray:
    """A street tree billboard: trunk and a noisy leafy crown, or bare branches dusted with snow."""
    v = ((np.arange(TREE_H) + 0.5) / TREE_H)[:, None]
    u = ((np.arange(TREE_W) + 0.5) / TREE_W)[None, :]
    trunk = (np.abs(u - 0.5) < 0.035 + 0.02 * (0.5 - v)) & (v < 0.55)
    crown_noise = _periodic_noise(rng, TREE_H, TREE_W, 3.0)
    shade = _periodic_noise(rng, TREE_H, TREE_W, 1.2)
    cy, ry, rx = rng.uniform(0.6, 0.68), rng.uniform(0.3, 0.37), rng.uniform(0.4, 0.48)
    r = np.sqrt(((u - 0.5) / rx) ** 2 + ((v - cy) / ry) ** 2)
    leaf = np.array((0.2, 0.36, 0.13), np.float32) * np.float32(rng.uniform(0.8, 1.2))
    angles = rng.uniform(-1.1, 1.1, 7)
    heights = rng.uniform(0.35, 0.6, 7)
    if not bare:
        crown = r + 0.28 * crown_noise < 1.0
        light = np.clip(0.75 + 0.25 * shade + 0.6 * (v - cy), 0.35, 1.3)
        rgb = np.where(crown[..., None], leaf * light[..., None], np.array((0.3, 0.24, 0.18), np.float32))
        alpha = crown | trunk
    else:
        branches = np.zeros((TREE_H, TREE_W), bool)
        for angle, h in zip(angles, heights):
            t = np.linspace(0.0, 1.0, 60)
            bu = 0.5 + np.sin(angle) * 0.45 * t
            bv = h + np.cos(angle) * 0.4 * t
            rows = np.clip((bv * TREE_H).astype(np.int64), 0, TREE_H - 1)
            cols = np.clip((bu * TREE_W).astype(np.int64), 0, TREE_W - 1)
            branches[rows, cols] = True
        twigs = (r + 0.28 * crown_noise < 1.0) & (shade > 1.2)
        alpha = trunk | branches | twigs
        rgb = np.broadcast_to(np.array((0.24, 0.21, 0.19), np.float32), (TREE_H, TREE_W, 3)).copy()
        top = alpha & ~np.roll(alpha, -1, axis=0)  # texel with nothing above it: snow settles there
        rgb[top & (rng.random((TREE_H, TREE_W)) < 0.6)] = _SNOW
    return _pack(rgb, alpha.astype(np.float32), np.zeros((TREE_H, TREE_W), np.float32))


def _paint_lamp() -> np.ndarray:
    """A street lamp billboard: a dark pole with a lamp head whose underside glows (emission)."""
    z = ((np.arange(LAMP_H) + 0.5) / PX_PER_M)[:, None]
    u = ((np.arange(LAMP_W) + 0.5) / PX_PER_M)[None, :]
    pole = (np.abs(u - 0.8) < 0.1) & (z < 7.3)
    head = (np.abs(u - 0.8) < 0.45) & (z > 7.0) & (z < 7.45)
    bulb = head & (z < 7.15)
    alpha = pole | head
    rgb = np.where(bulb[..., None], np.array((1.0, 0.92, 0.75), np.float32), np.array((0.17, 0.18, 0.19), np.float32))
    rgb = np.broadcast_to(rgb, (LAMP_H, LAMP_W, 3))
    return _pack(rgb, alpha.astype(np.float32), bulb.astype(np.float32))


def _pack(rgb: np.ndarray, alpha: np.ndarray, emission: np.ndarray) -> np.ndarray:
    """RGB albedo, alpha and emission in [0, 1] as one uint8 [H, W, 5] texel block."""
    stacked = np.concatenate([np.clip(rgb, 0, 1), alpha[..., None], emission[..., None]], axis=2)
    return np.round(stacked * 255.0).astype(np.uint8)


def _paint_atlas(world: World, snow: bool) -> Atlas:
    """All templates of the world painted into one atlas (the snowy variant has snowy ledges and bare trees)."""
    widths = np.array([w for w, _ in world.template_sizes], dtype=np.int64)
    heights = np.array([h for _, h in world.template_sizes], dtype=np.int64)
    col0 = np.concatenate([[0], np.cumsum(widths)[:-1]])
    texels = np.zeros((int(heights.max()), int(widths.sum()), 5), np.uint8)
    for k, (kind, index) in enumerate(world.template_kinds):
        if kind == "facade":
            block = _paint_facade(_facade_rng(world.seed, index), snow)
        elif kind == "side":
            block = _paint_side_wall(np.random.default_rng([world.seed, 4, index]), snow)
        elif kind == "tree":
            block = _paint_tree(np.random.default_rng([world.seed, 5, index]), snow)
        else:
            block = _paint_lamp()
        texels[: block.shape[0], col0[k] : col0[k] + block.shape[1]] = block
    return Atlas(np.ascontiguousarray(texels.transpose(1, 0, 2)), col0, widths, heights)


def _splat_lamps(world: World) -> np.ndarray:
    """Ground illumination of all street lamps (1 under a lamp, a pool of about LAMP_POOL metres) as a raster."""
    nx = int(math.ceil((world.xs[-1] + 2 * _LIGHT_MARGIN) / LIGHT_RES))
    ny = int(math.ceil((world.ys[-1] + 2 * _LIGHT_MARGIN) / LIGHT_RES))
    light = np.zeros((ny + 1, nx + 1), np.float32)
    radius = int(22.0 / LIGHT_RES)
    offs = np.arange(-radius, radius + 1) * LIGHT_RES
    r2 = offs[:, None] ** 2 + offs[None, :] ** 2
    kernel = (1.0 / (1.0 + r2 / LAMP_POOL**2) ** 1.5).astype(np.float32)
    for x, y in world.lamps:
        cx, cy = int(round((x + _LIGHT_MARGIN) / LIGHT_RES)), int(round((y + _LIGHT_MARGIN) / LIGHT_RES))
        light[cy - radius : cy + radius + 1, cx - radius : cx + radius + 1] += kernel
    return light


# ----------------------------------------------------------------------------------------------- routes


def route(world: World, which: str) -> np.ndarray:
    """Polyline [M, 2] (metres) of the ``train`` or ``test`` route in its driving lane; closed (last == first).

    It starts just before a junction, laps one block clockwise, drives through that junction again the same way
    (a loop) and then a long circuit back to the start.
    """
    if which not in _ROUTE_COLUMNS:
        raise ValueError(f"route must be 'train' or 'test', got {which!r}")
    nodes = [np.array([world.xs[i], world.ys[j]]) for (i, j), _ in _route_edges(which)]
    n = len(nodes)
    corners = []
    for k in range(n):
        prev, here, nxt = nodes[k - 1], nodes[k], nodes[(k + 1) % n]
        d_in = (here - prev) / np.linalg.norm(here - prev)
        d_out = (nxt - here) / np.linalg.norm(nxt - here)
        r_in, r_out = np.array([d_in[1], -d_in[0]]), np.array([d_out[1], -d_out[0]])  # right normals
        if abs(d_in @ d_out) > 0.999:
            corners.append((here + DRIVE_LANE * r_in, d_in, d_out))
        else:  # intersection of the two lane lines
            a = here + DRIVE_LANE * r_in
            b = here + DRIVE_LANE * r_out
            t = _cross(b - a, d_out) / _cross(d_in, d_out)
            corners.append((a + t * d_in, d_in, d_out))
    points: list[np.ndarray] = []
    for corner, d_in, d_out in corners:
        if abs(d_in @ d_out) > 0.999:
            points.append(corner)
            continue
        turn = np.sign(_cross(d_in, d_out))  # + = left
        start = corner - ROUTE_RADIUS * d_in
        centre = start + turn * ROUTE_RADIUS * np.array([-d_in[1], d_in[0]])
        a0 = math.atan2(*(start - centre)[::-1])
        for t in np.linspace(0.0, 1.0, 13):
            angle = a0 + turn * t * math.pi / 2
            points.append(centre + ROUTE_RADIUS * np.array([math.cos(angle), math.sin(angle)]))
    # start a little before the first node, on the closing edge
    closing = corners[0][0] - corners[-1][0]
    start = corners[0][0] - ROUTE_LEAD_IN * closing / np.linalg.norm(closing)
    polyline = np.array([start, *points, start])
    keep = np.concatenate([[True], np.linalg.norm(np.diff(polyline, axis=0), axis=1) > 1e-6])
    return polyline[keep]


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    """z of the cross product of two 2-D vectors (> 0 when b turns left from a)."""
    return float(a[0] * b[1] - a[1] * b[0])


def _arc_lengths(polyline: np.ndarray) -> np.ndarray:
    """Cumulative distance along a polyline, starting at 0."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(polyline, axis=0), axis=1))])


def _along(polyline: np.ndarray, cum: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points at arc lengths ``s`` along the polyline (linear interpolation)."""
    return np.stack([np.interp(s, cum, polyline[:, 0]), np.interp(s, cum, polyline[:, 1])], axis=1)


def speed_profile(drive: Drive, n_frames: int) -> np.ndarray:
    """Relative speed per frame: smooth random variation of +-``speed_variation`` and ``stops`` full stops.

    A stop (3-5 s standing, 2.5 s braking and as long pulling away) needs about 12 s of drive: a drive too short for
    its stops makes as many as fit.
    """
    rng = np.random.default_rng([drive.seed, 11])
    t = np.arange(n_frames) / drive.fps
    speed = np.ones(n_frames)
    if drive.speed_variation > 0:
        wobble = np.zeros(n_frames)
        for period in (25.0, 47.0, 90.0):
            wobble += np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
        speed = 1.0 + drive.speed_variation * wobble / np.abs(wobble).max()
    stops = min(drive.stops, int(n_frames / (12.0 * drive.fps)))
    if stops > 0:
        centres = (np.arange(stops) + 0.5) / stops * n_frames
        centres += rng.uniform(-0.2, 0.2, stops) * n_frames / stops
        for c in centres:
            hold = rng.uniform(3.0, 5.0) * drive.fps / 2  # half the stop, frames
            ramp = 2.5 * drive.fps
            gap = np.abs(np.arange(n_frames) - c)
            envelope = np.clip((gap - hold) / ramp, 0.0, 1.0)
            speed = speed * (np.sin(envelope * np.pi / 2) ** 2)
    return np.maximum(speed, 0.0)


def drive_poses(route_xy: np.ndarray, drive: Drive, n_frames: int) -> Poses:
    """Where the camera is in each frame: the drive's speed profile integrated along the route, shifted sideways.

    The drive covers the same distance as a constant-speed drive (``n_frames`` x mean_speed / fps) whatever its
    speed profile; on a closed route it goes round again past the end.
    """
    if n_frames < 1:
        raise ValueError("n_frames must be at least 1")
    cum = _arc_lengths(route_xy)
    length = cum[-1]
    closed = np.linalg.norm(route_xy[0] - route_xy[-1]) < 1.0
    step = drive.mean_speed / drive.fps
    speed = speed_profile(drive, n_frames)
    increments = speed[:-1]
    if n_frames > 1 and increments.sum() > 0:
        increments = increments * (n_frames - 1) / increments.sum()
    arc = np.concatenate([[0.0], np.cumsum(increments)]) * step
    if arc[-1] > length and not closed:
        raise ValueError(f"the route is {length:.0f} m long, the drive needs {arc[-1]:.0f} m")
    s = arc % length if closed else arc
    ahead = _along(route_xy, cum, (s + 1.0) % length if closed else np.minimum(s + 1.0, length))
    behind = _along(route_xy, cum, (s - 1.0) % length if closed else np.maximum(s - 1.0, 0.0))
    tangent = ahead - behind
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    positions = _along(route_xy, cum, s) + drive.lateral_offset * left
    headings = np.degrees(np.arctan2(tangent[:, 0], tangent[:, 1])) % 360.0
    return Poses(positions, headings, np.arange(n_frames) / drive.fps, arc)


# ----------------------------------------------------------------------------------------------- rendering


@dataclass
class _Camera:
    """Pinhole camera geometry of one frame: position, forward and right vectors, per-column rays."""

    position: np.ndarray
    forward: np.ndarray
    right: np.ndarray
    focal: float
    horizon: float
    xc: np.ndarray  # [W] column offsets on the image plane (x / focal)
    rays: np.ndarray  # [W, 2] ray directions with unit forward component
    heading: float  # radians, compass


def _camera(position, heading_deg: float, width: int, height: int) -> _Camera:
    """The camera of a frame at ``position`` looking along compass ``heading_deg``."""
    h = math.radians(heading_deg)
    forward = np.array([math.sin(h), math.cos(h)])
    right = np.array([math.cos(h), -math.sin(h)])
    focal = (width / 2) / math.tan(math.radians(HFOV_DEG) / 2)
    xc = (np.arange(width) + 0.5 - width / 2) / focal
    rays = forward[None, :] + xc[:, None] * right[None, :]
    return _Camera(np.asarray(position, np.float64), forward, right, focal, HORIZON * height, xc, rays, h)


def _visible_quads(world: World, cam: _Camera) -> tuple[np.ndarray, ...]:
    """Walls facing the camera within range and field of view, plus camera-facing billboards of nearby sprites."""
    tan_half = math.tan(math.radians(HFOV_DEG) / 2) + 0.05
    p = world.panels
    mid = (p.p0 + p.p1) / 2 - cam.position
    half = np.linalg.norm(p.p1 - p.p0, axis=1) / 2
    fw = mid @ cam.forward
    lat = mid @ cam.right
    edge = p.p1 - p.p0
    facing = (cam.position[0] - p.p0[:, 0]) * edge[:, 1] - (cam.position[1] - p.p0[:, 1]) * edge[:, 0]
    keep = (fw + half > NEAR) & (fw - half < FAR) & (np.abs(lat) - half < (fw + half) * tan_half) & (facing > 0)
    walls = np.flatnonzero(keep)
    s = world.sprites
    rel = s.centre - cam.position
    sfw = rel @ cam.forward
    slat = rel @ cam.right
    near = (sfw > 0.8) & (sfw < FAR * 0.6) & (np.abs(slat) - s.width / 2 < sfw * tan_half)
    spr = np.flatnonzero(near)
    half_w = (s.width[spr] / 2)[:, None] * cam.right[None, :]
    p0 = np.concatenate([p.p0[walls], s.centre[spr] - half_w])
    p1 = np.concatenate([p.p1[walls], s.centre[spr] + half_w])
    top = np.concatenate([p.top[walls], s.height[spr]])
    template = np.concatenate([p.template[walls], s.template[spr]])
    u0 = np.concatenate([p.u0[walls], s.width[spr]])  # a billboard's u0 is its width
    tint = np.concatenate([p.tint[walls], np.ones((len(spr), 3), np.float32)])
    sunlit = np.concatenate([p.sunlit[walls], np.full(len(spr), 0.6, np.float32)])
    roofline = np.concatenate([p.roofline[walls], np.zeros(len(spr), bool)])
    sprite = np.concatenate([np.zeros(len(walls), bool), np.ones(len(spr), bool)])
    return p0, p1, top, template, u0, tint, sunlit, roofline, sprite


# The per-pixel work runs in numba kernels; a condition's look travels to them as one float vector.
_L_AMBIENT, _L_SUN, _L_ZENITH, _L_HORIZON, _L_CLOUDS, _L_CLOUD_COLOR = 0, 3, 4, 7, 10, 11
_L_FOG, _L_VISIBILITY, _L_SKY_FOG, _L_LAMPS, _L_WINDOWS, _L_HEADLIGHTS = 14, 17, 18, 19, 20, 21
_L_SNOW, _L_RAIN, _L_DUSK = 22, 23, 24


def _look_vector(look: Look) -> np.ndarray:
    """A look packed as the float vector the kernels read (layout in the _L_* offsets)."""
    return np.array([
        *look.ambient, look.sun, *look.zenith, *look.horizon, look.clouds, *look.cloud_color, *look.fog,
        look.visibility, look.sky_fog, look.lamps, look.windows, look.headlights, float(look.snow),
        float(look.rain), look.dusk_glow,
    ], dtype=np.float64)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _smooth(edge0: float, edge1: float, x: float) -> float:
    """Hermite step from 0 at edge0 to 1 at edge1 (scalar)."""
    t = min(max((x - edge0) / (edge1 - edge0), 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _wrap(x: float, period: float) -> float:
    """``x`` modulo a positive ``period``, in [0, period)."""
    return x - period * math.floor(x / period)


def _line_table(lines: np.ndarray) -> np.ndarray:
    """Index of the nearest line for every metre from ``lines[0] - _TABLE_MARGIN`` (a lookup for the kernels)."""
    centres = lines[0] - _TABLE_MARGIN + 0.5 + np.arange(int(lines[-1] - lines[0] + 2 * _TABLE_MARGIN))
    return np.abs(centres[:, None] - lines[None, :]).argmin(axis=1).astype(np.int64)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _offset_to_line(lines: np.ndarray, table: np.ndarray, v: float) -> float:
    """Signed offset of ``v`` from the nearest of the sorted ``lines`` (table lookup, then the neighbours)."""
    cell = min(max(int(math.floor(v - lines[0] + _TABLE_MARGIN)), 0), len(table) - 1)
    i = table[cell]
    best = v - lines[i]
    if i > 0 and abs(v - lines[i - 1]) < abs(best):
        best = v - lines[i - 1]
    if i + 1 < len(lines) and abs(v - lines[i + 1]) < abs(best):
        best = v - lines[i + 1]
    return best


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bilinear(texture: np.ndarray, x: float, y: float) -> float:
    """Bilinear sample of a 256x256 tiling texture at texel coordinates (x, y)."""
    fx, fy = math.floor(x), math.floor(y)
    wx, wy = x - fx, y - fy
    x0, y0 = int(fx) & 255, int(fy) & 255
    x1, y1 = (x0 + 1) & 255, (y0 + 1) & 255
    top = texture[y0, x0] * (1 - wx) + texture[y0, x1] * wx
    return top * (1 - wy) + (texture[y1, x0] * (1 - wx) + texture[y1, x1] * wx) * wy


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lamp_at(light: np.ndarray, x: float, y: float) -> float:
    """Street-lamp light on the ground at (x, y): nearest cell of the light map."""
    ix = int((x + _LIGHT_MARGIN) / LIGHT_RES + 0.5)
    iy = int((y + _LIGHT_MARGIN) / LIGHT_RES + 0.5)
    ix = min(max(ix, 0), light.shape[1] - 1)
    iy = min(max(iy, 0), light.shape[0] - 1)
    return light[iy, ix]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _headlight_at(depth: float, lateral: float, z: float) -> float:
    """Low-beam headlight on a point ``depth`` ahead, ``lateral`` to the side, ``z`` high: a cone fading by ~30 m."""
    w = (lateral + 0.3) / (0.28 * depth + 1.2)
    reach = _smooth(1.0, 4.0, depth) / (1.0 + (depth / 11.0) ** 2)
    return 2.2 * math.exp(-w * w) * reach * math.exp(-max(z - 0.6, 0.0) / (0.06 * depth + 0.6))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _ground_albedo(gx: float, gy: float, xs, ys, x_table, y_table, noise, lk) -> tuple:
    """Albedo of a ground point: asphalt with lane markings and zebra crossings, kerb, paving, grass;
    snow with slushy wheel tracks in winter, darker and puddled in rain."""
    dx = _offset_to_line(xs, x_table, gx)
    dy = _offset_to_line(ys, y_table, gy)
    ax, ay = abs(dx), abs(dy)
    if ax <= ay:
        lat, along, cross, dist = dx, gy, ay, ax
    else:
        lat, along, cross, dist = dy, gx, ax, ay
    al = abs(lat)
    fine = _bilinear(noise[0], gx * 6.0, gy * 6.0)
    mid = _bilinear(noise[1], gx * 6.0, gy * 6.0)
    coarse = _bilinear(noise[1], gx * 1.5, gy * 1.5)
    road = dist < ROAD_HALF
    junction = ax < ROAD_HALF and ay < ROAD_HALF
    marking = False
    if road and not junction and cross > ROAD_HALF + 0.5:
        if al < 0.08 or abs(al - (ROAD_HALF - 0.3)) < 0.08:
            marking = True
        elif abs(al - LANE) < 0.07 and _wrap(along, 9.0) < 3.0:
            marking = True
        elif ROAD_HALF + 1.5 < cross < ROAD_HALF + 4.5 and _wrap(lat, 1.2) < 0.6 and al < ROAD_HALF - 0.4:
            marking = True
    kerb = (not road) and dist < ROAD_HALF + 0.25
    sidewalk = (not road) and (not kerb) and dist < SETBACK
    grain = 1.0 + 0.06 * fine + 0.06 * mid + 0.04 * coarse
    if lk[_L_SNOW] > 0.5:
        if road:
            slush = 0.0  # wheel tracks of the two lanes each way, and trodden patches in junctions
            for centre in (1.6, DRIVE_LANE):
                for side in (-0.8, 0.8):
                    slush = max(slush, 1.0 - _smooth(0.15, 0.35 + 0.1 * mid, abs(al - centre - side)))
            if junction:
                slush = max(slush, 0.7 * _smooth(0.0, 0.8, coarse))
            r = 0.78 - 0.2 * slush
            g = 0.79 - 0.21 * slush
            b = 0.82 - 0.23 * slush
        elif kerb:
            r, g, b = 0.8, 0.81, 0.84
        else:
            r, g, b = 0.88, 0.89, 0.92
        return r * grain, g * grain, b * grain
    if road:
        if marking:
            m = 0.8 * (0.88 + 0.08 * fine)
            r, g, b = m, m, m * 0.97
        else:
            r, g, b = 0.26, 0.26, 0.27
    elif kerb:
        r, g, b = 0.6, 0.6, 0.58
    elif sidewalk:
        if _wrap(along, 1.5) < 0.06 or _wrap(lat, 1.5) < 0.06:
            r, g, b = 0.38, 0.37, 0.35
        else:
            r, g, b = 0.5, 0.48, 0.45
    else:
        k = 1.0 + 0.25 * coarse
        r, g, b = 0.27 * k, 0.33 * k, 0.17 * k
    r, g, b = r * grain, g * grain, b * grain
    if lk[_L_RAIN] > 0.5 and (road or sidewalk):
        r, g, b = r * 0.62, g * 0.62, b * 0.62
        wet = 0.6 * _smooth(1.2, 1.6, coarse)  # puddles mirror the sky
        r = r * (1 - wet) + lk[_L_HORIZON] * 0.8 * wet
        g = g * (1 - wet) + lk[_L_HORIZON + 1] * 0.8 * wet
        b = b * (1 - wet) + lk[_L_HORIZON + 2] * 0.8 * wet
    return r, g, b


@njit(cache=True, nogil=True, error_model="numpy")
def _sky_color(elevation: float, azimuth: float, clouds, lk) -> tuple:
    """Sky colour in a direction: horizon-to-zenith gradient, panorama clouds, a dusk glow in the west."""
    g = min(max(elevation / 0.6109, 0.0), 1.0)  # 35 degrees
    g = g * (2.0 - g)
    r = lk[_L_HORIZON] * (1 - g) + lk[_L_ZENITH] * g
    gg = lk[_L_HORIZON + 1] * (1 - g) + lk[_L_ZENITH + 1] * g
    b = lk[_L_HORIZON + 2] * (1 - g) + lk[_L_ZENITH + 2] * g
    if lk[_L_CLOUDS] > 0:
        ri = min(max(int(elevation / (math.pi / 2) * clouds.shape[0] * 1.8), 0), clouds.shape[0] - 1)
        ci = int(azimuth / (2 * math.pi) * clouds.shape[1]) % clouds.shape[1]
        c = clouds[ri, ci]
        cover = _smooth(0.5, 0.75, c) * lk[_L_CLOUDS]
        lum = 0.85 + 0.3 * (c - 0.5)
        r = r * (1 - cover) + lk[_L_CLOUD_COLOR] * lum * cover
        gg = gg * (1 - cover) + lk[_L_CLOUD_COLOR + 1] * lum * cover
        b = b * (1 - cover) + lk[_L_CLOUD_COLOR + 2] * lum * cover
    if lk[_L_DUSK] > 0:
        diff = (azimuth - 4.3633 + math.pi) % (2 * math.pi) - math.pi  # sun set in the west-south-west (250 deg)
        glow = lk[_L_DUSK] * math.exp(-(diff / 0.7) ** 2) * math.exp(-max(elevation, 0.0) / 0.12)
        r, gg, b = r + glow, gg + 0.55 * glow, b + 0.25 * glow
    f = lk[_L_SKY_FOG]
    return (r * (1 - f) + lk[_L_FOG] * f, gg * (1 - f) + lk[_L_FOG + 1] * f, b * (1 - f) + lk[_L_FOG + 2] * f)


@njit(cache=True, nogil=True, error_model="numpy")
def _sky_panorama(clouds, lk):
    """The sky of a look at every (tan elevation, azimuth) step, so a sky pixel is one lookup."""
    rows, cols = int(1.5 / SKY_STEP), clouds.shape[1]
    sky = np.empty((rows, cols, 3), np.float32)
    for i in range(rows):
        elevation = math.atan((i + 0.5) * SKY_STEP)
        for j in range(cols):
            r, g, b = _sky_color(elevation, (j + 0.5) / cols * 2 * math.pi, clouds, lk)
            sky[i, j, 0], sky[i, j, 1], sky[i, j, 2] = r, g, b
    return sky


@njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _raycast_kernel(cx, cy, rays, p0, p1, depth, quad, along):
    """For every column, the nearest few quads its ray hits, sorted by depth (inf where fewer are hit)."""
    width, layers = depth.shape
    for c in range(width):
        for k in range(layers):
            depth[c, k] = np.inf
            quad[c, k] = 0
            along[c, k] = 0.0
        dx, dy = rays[c, 0], rays[c, 1]
        for q in range(p0.shape[0]):
            ex, ey = p1[q, 0] - p0[q, 0], p1[q, 1] - p0[q, 1]
            denom = dx * ey - dy * ex
            if denom == 0.0:
                continue
            wx, wy = p0[q, 0] - cx, p0[q, 1] - cy
            t = (wx * ey - wy * ex) / denom
            if t <= NEAR or t >= FAR or t >= depth[c, layers - 1]:
                continue
            s = (wx * dy - wy * dx) / denom
            if s < 0.0 or s > 1.0:
                continue
            k = layers - 1
            while k > 0 and depth[c, k - 1] > t:
                depth[c, k], quad[c, k], along[c, k] = depth[c, k - 1], quad[c, k - 1], along[c, k - 1]
                k -= 1
            depth[c, k], quad[c, k], along[c, k] = t, q, s * math.sqrt(ex * ex + ey * ey)


@njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _shade_pixels(color, emission, horizon, focal, cx, cy, heading, rays, xc, depth, quad, along,
                  q_top, q_tpl, q_u0, q_tint, q_sun, q_roof, q_sprite, texels, col0, tw, th,
                  xs, ys, x_table, y_table, noise, light, sky, lk):
    """Every pixel's lit, fogged colour and its emission, column by column: the first opaque quad texel among
    the column's nearest hits that covers the row, else the floor below the horizon, else the sky."""
    height, width = emission.shape
    layers = depth.shape[1]
    lamps, windows, headlights = lk[_L_LAMPS], lk[_L_WINDOWS], lk[_L_HEADLIGHTS]
    sun, visibility = lk[_L_SUN], lk[_L_VISIBILITY]
    snow = lk[_L_SNOW] > 0.5
    # per hit of the current column: rows covered, texture column and scale, depth-dependent light and fog
    r0 = np.empty(layers, np.int64)
    r1 = np.empty(layers, np.int64)
    tex_col = np.empty(layers, np.int64)
    z_scale = np.empty(layers, np.float64)
    z_slope = np.empty(layers, np.float64)
    keep = np.empty(layers, np.float64)
    shade0 = np.empty(layers, np.float64)
    lamp0 = np.empty(layers, np.float64)
    head0 = np.empty(layers, np.float64)
    beam = np.empty(layers, np.float64)
    ground_t = np.empty(height, np.float64)
    for r in range(height):
        below = r + 0.5 - horizon
        ground_t[r] = CAMERA_HEIGHT * focal / below if below > 0.5 else np.inf
    for c in range(width):
        norm = math.sqrt(1.0 + xc[c] * xc[c])
        azimuth = (heading + math.atan(xc[c])) % (2 * math.pi)
        ci = min(int(azimuth / (2 * math.pi) * sky.shape[1]), sky.shape[1] - 1)
        n_hits = 0
        for k in range(layers):
            t = depth[c, k]
            if not t < 1e30:
                break
            n_hits += 1
            q = quad[c, k]
            tpl = q_tpl[q]
            y_top = horizon - (q_top[q] - CAMERA_HEIGHT) * focal / t
            y_bottom = horizon + CAMERA_HEIGHT * focal / t
            r0[k] = min(max(int(math.ceil(y_top - 0.5)), 0), height)
            r1[k] = min(max(int(math.ceil(y_bottom - 0.5)), 0), height)
            length = along[c, k]
            if q_sprite[q]:
                u_scale, z_scale[k] = tw[tpl] / q_u0[q], th[tpl] / q_top[q]  # sprites keep their width in u0
                tex_col[k] = col0[tpl] + min(int(length * u_scale), tw[tpl] - 1)
            else:
                z_scale[k] = float(PX_PER_M)
                tex_col[k] = col0[tpl] + int(math.floor((length + q_u0[q]) * PX_PER_M)) % tw[tpl]
            z_slope[k] = t / focal
            keep[k] = math.exp(-t * norm / visibility)
            shade0[k] = 1.0 - sun + sun * (0.45 + 0.9 * q_sun[q])
            lamp0[k] = 0.9 * _lamp_at(light, cx + t * rays[c, 0], cy + t * rays[c, 1]) if lamps > 0 else 0.0
            head0[k] = _headlight_at(t, xc[c] * t, 0.6) if headlights > 0 else 0.0
            beam[k] = 0.06 * t + 0.6
        for r in range(height):
            drawn = False
            ar = ag = ab = em = fog_keep = shade = lamp = head = 0.0
            for k in range(n_hits):
                if r < r0[k] or r >= r1[k]:
                    continue
                q = quad[c, k]
                tpl = q_tpl[q]
                z = CAMERA_HEIGHT + (horizon - r - 0.5) * z_slope[k]
                row = min(max(int(math.floor(z * z_scale[k])), 0), th[tpl] - 1)
                col = tex_col[k]
                if texels[col, row, 3] < 128:
                    continue
                ar = texels[col, row, 0] * (q_tint[q, 0] / 255.0)
                ag = texels[col, row, 1] * (q_tint[q, 1] / 255.0)
                ab = texels[col, row, 2] * (q_tint[q, 2] / 255.0)
                if q_roof[q] and z > q_top[q] - 0.35:
                    if snow:
                        ar, ag, ab = 0.93, 0.94, 0.97
                    else:
                        ar, ag, ab = ar * 0.6, ag * 0.6, ab * 0.6
                em = texels[col, row, 4] / 255.0
                fog_keep = keep[k]
                shade = shade0[k] * (0.72 + 0.28 * min(max(z / 2.5, 0.0), 1.0))
                if lamps > 0:
                    lamp = lamp0[k] * math.exp(-max(z - 1.0, 0.0) / 6.0)
                if headlights > 0:
                    head = head0[k] * math.exp(-max(z - 0.6, 0.0) / beam[k])
                drawn = True
                break
            if not drawn:
                t = ground_t[r]
                if t < 1e30:
                    gx, gy = cx + t * rays[c, 0], cy + t * rays[c, 1]
                    ar, ag, ab = _ground_albedo(gx, gy, xs, ys, x_table, y_table, noise, lk)
                    fog_keep = math.exp(-t * norm / visibility)
                    shade = 1.0
                    if lamps > 0:
                        lamp = _lamp_at(light, gx, gy)
                    if headlights > 0:
                        head = _headlight_at(t, xc[c] * t, 0.0)
                else:  # the sky panorama, by tangent of the elevation and by azimuth
                    ri = min(int((horizon - r - 0.5) / (focal * norm) / SKY_STEP), sky.shape[0] - 1)
                    color[r, c, 0], color[r, c, 1], color[r, c, 2] = sky[ri, ci, 0], sky[ri, ci, 1], sky[ri, ci, 2]
                    emission[r, c] = 0.0
                    continue
            lr = lk[_L_AMBIENT] * shade + lamps * lamp + headlights * head * 0.95
            lg = lk[_L_AMBIENT + 1] * shade + lamps * lamp * 0.82 + headlights * head * 0.95
            lb = lk[_L_AMBIENT + 2] * shade + lamps * lamp * 0.6 + headlights * head
            pr, pg, pb = ar * lr, ag * lg, ab * lb
            if windows > 0 and em > 0:
                e = windows * em
                pr += e * (0.55 + 0.6 * ar)
                pg += e * (0.43 + 0.6 * ag)
                pb += e * (0.25 + 0.6 * ab)
            color[r, c, 0] = pr * fog_keep + lk[_L_FOG] * (1 - fog_keep)
            color[r, c, 1] = pg * fog_keep + lk[_L_FOG + 1] * (1 - fog_keep)
            color[r, c, 2] = pb * fog_keep + lk[_L_FOG + 2] * (1 - fog_keep)
            emission[r, c] = em * windows * fog_keep


@njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _finish_pixels(color, glow, factor, noise, oy, ox, sigma, exposure, out):
    """Camera output: add the (bilinearly upsampled) glow, exposure, sensor noise; clip and quantise to uint8."""
    height, width = out.shape[0], out.shape[1]
    gh, gw = glow.shape
    nh, nw = noise.shape[0], noise.shape[1]
    gx0 = np.empty(width, np.int64)
    gwx = np.empty(width, np.float64)
    nx = np.empty(width, np.int64)
    for c in range(width):
        fx = min(max((c + 0.5) / factor - 0.5, 0.0), gw - 1.0)
        gx0[c] = min(int(fx), max(gw - 2, 0))
        gwx[c] = fx - gx0[c]
        nx[c] = (c + ox) % nw
    for r in range(height):
        fy = min(max((r + 0.5) / factor - 0.5, 0.0), gh - 1.0)
        y0 = min(int(fy), max(gh - 2, 0))
        wy = fy - y0
        y1 = min(y0 + 1, gh - 1)
        ny = (r + oy) % nh
        for c in range(width):
            x0 = gx0[c]
            x1 = min(x0 + 1, gw - 1)
            wx = gwx[c]
            g = ((glow[y0, x0] * (1 - wx) + glow[y0, x1] * wx) * (1 - wy)
                 + (glow[y1, x0] * (1 - wx) + glow[y1, x1] * wx) * wy) * 0.6
            n = nx[c]
            v0 = (color[r, c, 0] + g) * exposure + sigma * noise[ny, n, 0]
            v1 = (color[r, c, 1] + g * 0.8) * exposure + sigma * noise[ny, n, 1]
            v2 = (color[r, c, 2] + g * 0.55) * exposure + sigma * noise[ny, n, 2]
            out[r, c, 0] = np.uint8(int(min(max(v0, 0.0), 1.0) * 255.0 + 0.5))
            out[r, c, 1] = np.uint8(int(min(max(v1, 0.0), 1.0) * 255.0 + 0.5))
            out[r, c, 2] = np.uint8(int(min(max(v2, 0.0), 1.0) * 255.0 + 0.5))


_SENSOR_NOISE: list[np.ndarray] = []


def _sensor_noise() -> np.ndarray:
    """A fixed field of unit Gaussian noise [256, 512, 3]; frames read it at random offsets (cheaper than drawing)."""
    if not _SENSOR_NOISE:
        _SENSOR_NOISE.append(np.random.default_rng(20240611).standard_normal((256, 512, 3)).astype(np.float32))
    return _SENSOR_NOISE[0]


def render_frame(world: World, position, heading_deg: float, condition: str, width: int, height: int,
                 rng: np.random.Generator) -> np.ndarray:
    """One camera image (uint8 [H, W, 3]) at ``position`` looking along compass ``heading_deg`` under a condition.

    ``rng`` adds this frame's sensor noise, exposure jitter and rain streaks.
    """
    if condition not in LOOKS:
        raise ValueError(f"condition {condition!r} is not known (choose from: {', '.join(CONDITIONS)})")
    look = LOOKS[condition]
    lk = _look_vector(look)
    cam = _camera(position, heading_deg, width, height)
    p0, p1, top, template, u0, tint, sunlit, roofline, sprite = _visible_quads(world, cam)
    depth = np.empty((width, LAYERS), np.float64)
    quad = np.empty((width, LAYERS), np.int64)
    along = np.empty((width, LAYERS), np.float64)
    cx, cy = float(cam.position[0]), float(cam.position[1])
    _raycast_kernel(cx, cy, cam.rays, p0, p1, depth, quad, along)
    atlas = world.atlas(look.snow)
    light = world.light_map() if look.lamps > 0 else np.zeros((1, 1), np.float32)
    x_table, y_table = world.line_tables()
    color = np.empty((height, width, 3), np.float32)
    emission = np.empty((height, width), np.float32)
    _shade_pixels(
        color, emission, cam.horizon, cam.focal, cx, cy, cam.heading, cam.rays, cam.xc, depth, quad, along,
        top, template, u0, tint, sunlit, roofline, sprite, atlas.texels, atlas.col0, atlas.width, atlas.height,
        world.xs, world.ys, x_table, y_table, world.ground_noise(), light, world.sky(condition), lk,
    )
    factor = 4
    glow = _blur(emission, factor) if look.windows > 0 else np.zeros((1, 1), np.float32)
    if look.rain:
        _rain_streaks(rng, color)
    noise = _sensor_noise()
    oy, ox = int(rng.integers(noise.shape[0])), int(rng.integers(noise.shape[1]))
    exposure = 1.0 + float(rng.normal(0.0, 0.03))
    out = np.empty((height, width, 3), np.uint8)
    _finish_pixels(color, glow.astype(np.float32), factor, noise, oy, ox, look.noise, exposure, out)
    return out


def _blur(image: np.ndarray, factor: int = 4) -> np.ndarray:
    """A wide blur of a [H, W] image at 1/``factor`` resolution: block-average down, two 3x3 box passes."""
    h, w = image.shape
    hp, wp = -(-h // factor) * factor, -(-w // factor) * factor
    padded = np.pad(image, ((0, hp - h), (0, wp - w)), mode="edge")
    small = padded.reshape(hp // factor, factor, wp // factor, factor).mean(axis=(1, 3))
    for _ in range(2):
        p = np.pad(small, 1, mode="edge")
        small = (p[:-2, 1:-1] + p[1:-1, 1:-1] + p[2:, 1:-1]) / 3
        p = np.pad(small, 1, mode="edge")
        small = (p[1:-1, :-2] + p[1:-1, 1:-1] + p[1:-1, 2:]) / 3
    return small


def _rain_streaks(rng: np.random.Generator, image: np.ndarray) -> None:
    """Draw faint slanted rain streaks over the image, in place."""
    h, w, _ = image.shape
    n = max(1, h * w // 300)
    length = max(3, h // 12)
    y0 = rng.uniform(-length, h, n)
    x0 = rng.uniform(0, w, n)
    bright = rng.uniform(0.06, 0.16, n).astype(np.float32)
    steps = np.arange(length)
    ys = np.round(y0[:, None] + steps[None, :]).astype(np.int64)
    xs = np.round(x0[:, None] + 0.18 * steps[None, :]).astype(np.int64)
    ok = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
    image[ys[ok], xs[ok]] += np.broadcast_to(bright[:, None], ys.shape)[ok][:, None]


# ----------------------------------------------------------------------------------------------- output


def render_traversal(world: World, route_xy: np.ndarray, drive: Drive, n_frames: int, out_dir: str | Path,
                     width: int = 320, height: int = 240,
                     progress: Callable[[int], None] | None = None) -> Path:
    """Render a drive along a route into an image folder with ``positions.csv``, written atomically; its path.

    Images are ``000000.jpg`` ...; the CSV has ``name,easting,northing,timestamp,heading,segment``. The folder is
    rendered under a temporary sibling name and renamed into place (replacing an existing folder).
    """
    out = Path(out_dir)
    poses = drive_poses(route_xy, drive, n_frames)
    with atomic_folder(out, "positions.csv") as tmp:
        names = []
        for i in range(n_frames):
            rng = np.random.default_rng([drive.seed, 12, i])
            image = render_frame(world, poses.positions[i], poses.headings[i], drive.condition, width, height, rng)
            name = f"{i:06d}.jpg"
            Image.fromarray(image).save(tmp / name, quality=90)
            names.append(name)
            if progress is not None:
                progress(1)
        _write_positions(tmp / "positions.csv", names, poses)
    return out


def _write_positions(path: Path, names: list[str], poses: Poses) -> None:
    """The positions CSV of a rendered traversal (one continuous segment)."""
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["name", "easting", "northing", "timestamp", "heading", "segment"])
        for name, (x, y), t, h in zip(names, poses.positions, poses.timestamps, poses.headings):
            writer.writerow([name, f"{x:.3f}", f"{y:.3f}", f"{t:.3f}", f"{h:.2f}", 0])


def demo_drives(query_condition: str = "night", seed: int = 0) -> tuple[Drive, Drive]:
    """The reference drive (day, lane 0, constant speed) and the query drive (condition, other lane, stops)."""
    reference = Drive(condition="day", seed=seed * 1000 + 1)
    query = Drive(condition=query_condition, lateral_offset=3.0, speed_variation=0.4, stops=2, seed=seed * 1000 + 2)
    return reference, query


def write_demo_world(out: Path, *, frames: int = 600, width: int = 320, height: int = 240, seed: int = 0,
                     query_condition: str = "night",
                     progress_factory: Callable[[int, str], Callable[[int], None]] | None = None) -> dict[str, Path]:
    """Render the demo data under ``out``: reference and query traversals of the train and test routes.

    The references drive by day in the route's lane at constant speed, the queries under ``query_condition`` one
    lane to the left (3 m) with a +-40 % speed and two stops (``demo_drives``); ``frames`` frames each, 2 m apart
    for the references. ``progress_factory(total, label)`` gives a tick called with the frames just rendered.
    Returns {"train_reference", "train_query", "test_reference", "test_query"} -> folder.
    """
    out = Path(out)
    world = build_world(seed)
    reference, query = demo_drives(query_condition, seed)
    paths: dict[str, Path] = {}
    for which in ("train", "test"):
        route_xy = route(world, which)
        for role, drive in (("reference", reference), ("query", query)):
            key = f"{which}_{role}"
            tick = progress_factory(frames, f"render {key}") if progress_factory else None
            paths[key] = render_traversal(world, route_xy, drive, frames, out / key, width, height, tick)
    return paths
