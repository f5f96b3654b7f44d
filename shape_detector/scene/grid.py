"""2D navigation grid of the floor (world frame, z up, metres), like ``nav_msgs/OccupancyGrid``.

Cells are ``-1`` unknown, ``0`` free, ``100`` occupied; row = y, column = x; ``origin`` is
the world (x, y) of the outer corner of cell (row 0, col 0).

* **free**: the floor was seen there (depth points within ``floor_band`` of ``floor_z``),
  accumulated over frames by :class:`FloorMemory`;
* **occupied**: under a part of an object (its primitives, else its box) that blocks an
  agent of height ``agent_height``: the part's bottom is below ``floor_z + agent_height``
  and its top above ``floor_z + min_height``. A table top higher than the agent leaves the
  space under it free and only its legs occupied (a small robot); a table top lower than the
  agent (a person, the default 1.8 m) occupies the whole footprint. A rug (top below
  ``min_height``) occupies nothing. A cell is occupied when its centre lies in a part's
  footprint, and the cell holding a part's centre always is (thin legs at coarse cells);
* **unknown** elsewhere.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from ..geometry import measured_depth

UNKNOWN, FREE, OCCUPIED = -1, 0, 100


@dataclass
class NavGrid:
    """A 2D floor grid in the world frame (see the module docstring)."""

    #: metres per cell
    resolution: float
    #: (2,) world x, y of the corner of cell (row 0, col 0)
    origin: np.ndarray
    #: (height, width) int8: -1 unknown, 0 free, 100 occupied; row = y, col = x
    data: np.ndarray
    #: world z of the floor, metres
    floor_z: float = 0.0

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(2)
        self.data = np.asarray(self.data, dtype=np.int8).reshape(np.shape(self.data)[0], -1) \
            if np.size(self.data) else np.zeros((0, 0), np.int8)

    @property
    def width(self) -> int:
        """Columns (along world x)."""
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        """Rows (along world y)."""
        return int(self.data.shape[0])

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(N,2) int (row, col) of world points ``xy`` (N,2); may lie outside the grid."""
        q = np.floor((np.asarray(xy, dtype=np.float64).reshape(-1, 2) - self.origin) / self.resolution)
        return q[:, ::-1].astype(np.int64)

    def cell_centers(self) -> np.ndarray:
        """(height, width, 2) world x, y of every cell centre."""
        xs = self.origin[0] + (np.arange(self.width) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(self.height) + 0.5) * self.resolution
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx, gy], axis=-1)

    def inflated(self, radius: float) -> NavGrid:
        """A copy with occupied cells grown by ``radius`` metres over free cells (unknown
        cells stay unknown)."""
        r = int(np.ceil(max(radius, 0.0) / self.resolution - 1e-9))
        occ = self.data == OCCUPIED
        if r == 0 or not occ.any():
            return NavGrid(self.resolution, self.origin.copy(), self.data.copy(), self.floor_z)
        grown = np.zeros_like(occ)
        h, w = occ.shape
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                if dx * dx + dy * dy > (radius / self.resolution) ** 2 + 1e-9:
                    continue
                grown[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] |= \
                    occ[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
        out = self.data.copy()
        out[grown & (out == FREE)] = OCCUPIED
        return NavGrid(self.resolution, self.origin.copy(), out, self.floor_z)


class FloorMemory:
    """Cells (world x, y) where the floor was seen, accumulated over frames.

    Stored as a growing boolean array of cells of ``resolution`` metres; cell ``(i, j)`` of
    the array is world cell ``(i + row0, j + col0)`` with world cell ``(r, c)`` spanning
    ``[c * res, (c + 1) * res) x [r * res, (r + 1) * res)``.
    """

    def __init__(self, resolution: float) -> None:
        self.resolution = float(resolution)
        self.seen = np.zeros((0, 0), dtype=bool)
        self.row0 = 0
        self.col0 = 0

    def add(self, xy: np.ndarray) -> None:
        """Mark the cells of floor points ``xy`` (N,2, world metres) as seen."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        xy = np.compress(np.isfinite(xy).all(axis=1), xy, axis=0)
        if len(xy) == 0:
            return
        rc = np.floor(xy[:, ::-1] / self.resolution).astype(np.int64)
        lo, hi = rc.min(0), rc.max(0)
        self._grow(lo, hi)
        self.seen[rc[:, 0] - self.row0, rc[:, 1] - self.col0] = True

    def _grow(self, lo: np.ndarray, hi: np.ndarray) -> None:
        h, w = self.seen.shape
        if h and lo[0] >= self.row0 and lo[1] >= self.col0 and hi[0] < self.row0 + h and hi[1] < self.col0 + w:
            return
        if h == 0:
            r0, c0, r1, c1 = lo[0], lo[1], hi[0] + 1, hi[1] + 1
        else:
            pad = 20  # grow in steps so a slowly panning camera does not reallocate each frame
            r0 = min(self.row0, lo[0] - pad) if lo[0] < self.row0 else self.row0
            c0 = min(self.col0, lo[1] - pad) if lo[1] < self.col0 else self.col0
            r1 = max(self.row0 + h, hi[0] + 1 + pad) if hi[0] >= self.row0 + h else self.row0 + h
            c1 = max(self.col0 + w, hi[1] + 1 + pad) if hi[1] >= self.col0 + w else self.col0 + w
        out = np.zeros((int(r1 - r0), int(c1 - c0)), dtype=bool)
        if h:
            out[self.row0 - r0:self.row0 - r0 + h, self.col0 - c0:self.col0 - c0 + w] = self.seen
        self.seen, self.row0, self.col0 = out, int(r0), int(c0)

    def contains(self, row0: int, col0: int, shape: tuple[int, ...]) -> np.ndarray:
        """(rows, cols) bool: which world cells of the window starting at cell (``row0``,
        ``col0``) were seen."""
        out = np.zeros(shape[:2], dtype=bool)
        h, w = self.seen.shape
        r0, c0 = max(row0, self.row0), max(col0, self.col0)
        r1, c1 = min(row0 + shape[0], self.row0 + h), min(col0 + shape[1], self.col0 + w)
        if r1 > r0 and c1 > c0:
            out[r0 - row0:r1 - row0, c0 - col0:c1 - col0] = self.seen[r0 - self.row0:r1 - self.row0,
                                                                      c0 - self.col0:c1 - self.col0]
        return out

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """World cell (row, col) range ``[lo, hi)`` of the seen cells, or None."""
        if not self.seen.any():
            return None
        rows = np.flatnonzero(self.seen.any(1))
        cols = np.flatnonzero(self.seen.any(0))
        return (np.array([rows[0] + self.row0, cols[0] + self.col0]),
                np.array([rows[-1] + 1 + self.row0, cols[-1] + 1 + self.col0]))


def floor_points(depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, floor_z: float,
                 band: float = 0.05, stride: int = 4, max_range: float = 6.0) -> np.ndarray:
    """World (x, y) (N,2) of the depth pixels (every ``stride``-th row and column, depth in
    metres, NaN/0 invalid) whose world z lies within ``band`` of ``floor_z`` and whose range
    is below ``max_range`` metres."""
    pts = depth_points_world(depth, K, T_world_camera, stride, max_range)
    return pts[np.abs(pts[:, 2] - floor_z) <= band, :2]


def floor_cells_seen(depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, floor_z: float,
                     resolution: float, near_xy: np.ndarray, band: float = 0.05,
                     known: FloorMemory | None = None) -> np.ndarray:
    """World (x, y) (N,2) of the centres of the cells around the floor points ``near_xy``
    (N,2) whose floor point projects onto a depth pixel that measures it (within ``band``
    along the optical axis, plus 1% of the range): dense free cells from sparse samples.
    Cells ``known`` (a memory of the same resolution) has seen already are not tested again."""
    if len(near_xy) == 0:
        return np.zeros((0, 2))
    lo = np.floor(near_xy.min(0) / resolution) - 1
    hi = np.floor(near_xy.max(0) / resolution) + 2
    xs = (np.arange(lo[0], hi[0]) + 0.5) * resolution
    ys = (np.arange(lo[1], hi[1]) + 0.5) * resolution
    gx, gy = np.meshgrid(xs, ys)
    if known is not None and known.seen.size:
        fresh = ~known.contains(int(lo[1]), int(lo[0]), gx.shape)
        gx, gy = gx[fresh], gy[fresh]
    pw = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, floor_z)], axis=1)
    T = np.asarray(T_world_camera, dtype=np.float64)
    cam = (pw - T[:3, 3]) @ T[:3, :3]
    z = cam[:, 2]
    d = measured_depth(cam, depth, K, min_z=0.1)
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(d) & (np.abs(d - z) <= band + 0.01 * z)
    return np.compress(seen, pw[:, :2], axis=0)


def depth_points_world(depth: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, stride: int = 4,
                       max_range: float = 6.0) -> np.ndarray:
    """World points (N,3) of every ``stride``-th pixel (row-major) with valid depth (metres)
    below ``max_range``; ``K`` the depth's intrinsics, ``T_world_camera`` the optical frame's pose."""
    d = np.asarray(depth, dtype=np.float32)
    T = np.ascontiguousarray(T_world_camera, dtype=np.float64)
    s = max(int(stride), 1)
    out = np.empty((-(-d.shape[0] // s) * -(-d.shape[1] // s), 3))
    n = _depth_points(d, s, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), T, float(max_range), out)
    return out[:n]


@numba.njit(cache=True, nogil=True)
def _depth_points(depth, stride, fx, fy, cx, cy, T, max_range, out):  # pragma: no cover - compiled
    """:func:`depth_points_world` into ``out``; returns the number of points."""
    n = 0
    for v in range(0, depth.shape[0], stride):
        ry = (v - cy) / fy
        for u in range(0, depth.shape[1], stride):
            z = np.float64(depth[v, u])
            if z > 0.0 and z < max_range:  # NaN compares False
                x, y = (u - cx) / fx * z, ry * z
                for a in range(3):
                    out[n, a] = T[a, 0] * x + T[a, 1] * y + T[a, 2] * z + T[a, 3]
                n += 1
    return n


def estimate_floor_z(z: np.ndarray, bin_m: float = 0.02, min_share: float = 0.03) -> float | None:
    """World height of the floor from points' heights ``z`` (N,): the lowest pair of
    neighbouring ``bin_m`` bins holding at least ``min_share`` of the points (a floor's
    noise spreads it over two), refined around the fuller of the two (None when too few)."""
    z = np.asarray(z, dtype=np.float64)
    z = z[np.isfinite(z)]
    if len(z) < 200:
        return None
    lo = np.floor(z.min() / bin_m) * bin_m
    counts = np.append(np.bincount(((z - lo) / bin_m).astype(np.int64)), 0)
    big = np.flatnonzero(counts[:-1] + counts[1:] >= min_share * len(z))
    if len(big) == 0:
        return None
    k = int(big[0])
    k += int(counts[k + 1] > counts[k])
    # refine: the mean of the points of that bin and its neighbours
    sel = np.abs(z - (lo + (k + 0.5) * bin_m)) <= 1.5 * bin_m
    return float(np.mean(z[sel]))


def floor_from_estimates(estimates: Sequence[float], tol: float = 0.04, min_frames: int = 3,
                         min_share: float = 0.1) -> float | None:
    """World height of the floor from per-frame estimates (:func:`estimate_floor_z`): the
    median of the estimates within ``tol`` m of the lowest one that at least ``min_frames``
    and ``min_share`` of them agree with; the median of all while none has that support
    (None without estimates). A frame filled by a bed or a table top puts its "floor" on
    that surface, so many frames may agree on a level above the floor; frames that see the
    floor agree on the lowest level, and nothing real lies below it."""
    e = np.sort(np.asarray([x for x in estimates if x is not None and np.isfinite(x)], dtype=np.float64))
    if len(e) == 0:
        return None
    need = max(int(min_frames), int(np.ceil(min_share * len(e))))
    near = np.abs(e[:, None] - e[None, :]) <= tol  # (a few hundred estimates at most)
    supported = np.flatnonzero(near.sum(1) >= need)
    return float(np.median(e[near[supported[0]]] if supported.size else e))


def part_blocks(center: np.ndarray, size: np.ndarray, rotation: np.ndarray, floor_z: float,
                agent_height: float, min_height: float) -> bool:
    """Whether a cuboid (world frame) blocks an agent (see the module docstring)."""
    hz = 0.5 * float(np.abs(np.asarray(rotation)[2]) @ np.asarray(size))
    return center[2] - hz < floor_z + agent_height and center[2] + hz > floor_z + min_height


def footprint_mask(grid: NavGrid, center: np.ndarray, size: np.ndarray, rotation: np.ndarray) -> \
        tuple[slice, slice, np.ndarray] | None:
    """Cells of ``grid`` under a cuboid's footprint: (row slice, col slice, bool mask of that
    window), or None when outside the grid. The footprint is the cuboid's horizontal extent
    along its two most horizontal axes."""
    R = np.asarray(rotation, dtype=np.float64)
    ax = np.argsort(np.abs(R[2]))[:2]
    a = R[:2, ax]  # the two horizontal axes, projected
    a = a / np.maximum(np.linalg.norm(a, axis=0, keepdims=True), 1e-9)
    half = 0.5 * np.asarray(size, dtype=np.float64)[ax]
    ext = np.abs(a) @ half
    c = np.asarray(center, dtype=np.float64)[:2]
    rc_lo = grid.world_to_cell((c - ext)[None])[0]
    rc_hi = grid.world_to_cell((c + ext)[None])[0]
    r0, c0 = max(rc_lo[0], 0), max(rc_lo[1], 0)
    r1, c1 = min(rc_hi[0] + 1, grid.height), min(rc_hi[1] + 1, grid.width)
    if r1 <= r0 or c1 <= c0:
        return None
    xs = grid.origin[0] + (np.arange(c0, c1) + 0.5) * grid.resolution
    ys = grid.origin[1] + (np.arange(r0, r1) + 0.5) * grid.resolution
    gx, gy = np.meshgrid(xs - c[0], ys - c[1])
    l0 = gx * a[0, 0] + gy * a[1, 0]
    l1 = gx * a[0, 1] + gy * a[1, 1]
    m = (np.abs(l0) <= half[0] + 1e-9) & (np.abs(l1) <= half[1] + 1e-9)
    cc = grid.world_to_cell(c[None])[0]
    if r0 <= cc[0] < r1 and c0 <= cc[1] < c1:
        m[cc[0] - r0, cc[1] - c0] = True
    return slice(r0, r1), slice(c0, c1), m


def build_grid(floor: FloorMemory, parts: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], floor_z: float,
               agent_height: float = 1.8, min_height: float = 0.05, pad: int = 2) -> NavGrid:
    """The grid over the seen floor and the blocking ``parts`` ((center, size, rotation),
    world frame): free where ``floor`` saw the floor, occupied under blocking parts."""
    res = floor.resolution
    parts = [(np.asarray(c, float), np.asarray(s, float), np.asarray(R, float)) for c, s, R in parts]
    parts = [p for p in parts if part_blocks(*p, floor_z, agent_height, min_height)]
    lo_hi = floor.bounds()
    boxes = []
    for c, s, R in parts:
        ext = 0.5 * (np.abs(R[:2]) @ s)
        boxes.append((np.floor((c[:2] - ext) / res)[::-1], np.floor((c[:2] + ext) / res)[::-1] + 1))
    if lo_hi is not None:
        boxes.append(lo_hi)
    if not boxes:
        return NavGrid(res, np.zeros(2), np.zeros((0, 0), np.int8), floor_z)
    lo = np.min([b[0] for b in boxes], axis=0).astype(np.int64) - pad
    hi = np.max([b[1] for b in boxes], axis=0).astype(np.int64) + pad
    data = np.full((int(hi[0] - lo[0]), int(hi[1] - lo[1])), UNKNOWN, dtype=np.int8)
    if lo_hi is not None:  # the seen cells lie inside [lo, hi): copy that window of the memory
        f_lo, f_hi = lo_hi
        win = floor.seen[f_lo[0] - floor.row0:f_hi[0] - floor.row0, f_lo[1] - floor.col0:f_hi[1] - floor.col0]
        r, c = f_lo[0] - lo[0], f_lo[1] - lo[1]
        data[r:r + win.shape[0], c:c + win.shape[1]][win] = FREE
    grid = NavGrid(res, np.array([lo[1] * res, lo[0] * res]), data, floor_z)
    for c, s, R in parts:
        fm = footprint_mask(grid, c, s, R)
        if fm is not None:
            rs, cs, m = fm
            grid.data[rs, cs][m] = OCCUPIED
    return grid
