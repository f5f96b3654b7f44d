"""Shortest paths on the floor grid for an agent of a given radius, then smoothed.

World frame, metres; grid cells are int8 (-1 unknown, 0 free, 100 occupied), row = y,
col = x. What unknown cells mean is a choice (``unknown``):

* ``"interior"`` (default, as nav2's planners allow unknown space by default): unknown cells
  enclosed by the known cells (inside their morphological closing by a disc of
  ``INTERIOR_CLOSE`` m: floor hidden behind furniture, the strip under the walking camera,
  gaps between depth samples) are walkable at ``UNKNOWN_COST`` times the length, so paths
  prefer seen floor; unknown cells outside the known cells' extent (beyond the walls, which
  the grid does not hold) stay blocked. It finds paths on maps whose seen floor is patchy, at
  the price of paths that pass closer to furniture the map has not seen (measured in
  docs/experiments);
* ``"blocked"`` (the cautious choice): only seen free floor is walked on; unknown space may
  hold furniture the map has not seen;
* ``"free"``: every unknown cell is walkable (at ``UNKNOWN_COST``).

Traversable cells keep the radius (and the margins of :mod:`.margins`) from every blocked
cell. Where no such path exists, a plan may *squeeze*: pass up to :data:`SQUEEZE` closer to
the map's obstacles, without the margins and through the tracks the map doubts
(:func:`.margins.without_doubtful`), at :data:`SQUEEZE_COST` times the length. A narrow
passage that boxes a few centimetres too large close, or that a doubtful track closes, stays
usable, and only where it is needed (a costmap's lethal core with a costly band around it, as
in nav2). Steps within
:data:`COMFORT` beyond the full clearance cost more, up to :data:`COMFORT_COST` times more at
its inner edge (nav2's inflation cost), so plans keep to the middle of a passage where there
is room. The search is Dijkstra on the 8-connected cell graph (scipy's compiled graph search);
the cell path is then shortened by line of sight over the fully traversable cells and the
cells it already uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from ..scene.grid import NavGrid
from .margins import UNCERTAINTY, padded_grid, without_doubtful
from .scene_data import as_grid, load_scene

FREE_MAX = 50  # cells with values in [0, FREE_MAX) count as free (nav_msgs convention)
UNKNOWN_POLICIES = ("blocked", "interior", "free")
#: length multiplier of steps onto walkable unknown cells
UNKNOWN_COST = 2.0
#: metres beyond the agent's radius a start or goal may move onto traversable floor by default
SNAP_EXTRA = 0.2
#: radius (m) of the closing that decides which unknown cells are enclosed ("interior")
INTERIOR_CLOSE = 1.0
#: metres closer than the agent's radius a plan may pass to the map's obstacles (margins
#: left out) where no path keeps the full clearance; 0 = never
SQUEEZE = 0.02
#: length multiplier of steps onto cells only a squeeze reaches
SQUEEZE_COST = 20.0
#: metres beyond the agent's radius (and margins) within which steps cost more, so plans keep
#: to the middle of a passage where there is room (nav2's inflation cost); 0 = off
COMFORT = 0.1
#: extra length multiplier at the inner edge of that band (falling linearly to 0 at its outer edge)
COMFORT_COST = 3.0


def closing(mask: np.ndarray, radius_cells: float) -> np.ndarray:
    """Morphological closing of ``mask`` by a disc (two distance transforms; the grid's
    outside counts as empty)."""
    pad = int(np.ceil(radius_cells)) + 1
    m = np.pad(mask, pad)
    grown = ndimage.distance_transform_edt(~m) <= radius_cells
    return (ndimage.distance_transform_edt(grown) > radius_cells)[pad:-pad, pad:-pad]


def walkable(grid: NavGrid, unknown: str = "interior") -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool walkable cells before inflation and (H, W) float step cost multipliers
    (1 on seen floor, ``UNKNOWN_COST`` on walkable unknown cells); see the module doc."""
    if unknown not in UNKNOWN_POLICIES:
        raise ValueError(f"unknown={unknown!r}: expected one of {UNKNOWN_POLICIES}")
    data = np.asarray(grid.data)
    free = (data >= 0) & (data < FREE_MAX)
    unk = data < 0
    if unknown == "interior" and unk.any():
        unk &= closing(data >= 0, INTERIOR_CLOSE / float(grid.resolution))
    elif unknown == "blocked":
        unk = np.zeros_like(free)
    return free | unk, np.where(unk, UNKNOWN_COST, 1.0)


def clearance(grid: NavGrid, unknown: str = "interior") -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool walkable cells and (H, W) float metres from each cell's area to the nearest
    blocked cell: its centre's distance minus half a cell, since an obstacle may reach up to
    the edge of the cells it marks (inf everywhere when nothing is blocked)."""
    free, _ = walkable(grid, unknown)
    return free, _distance(free, float(grid.resolution))


def _distance(free: np.ndarray, res: float) -> np.ndarray:
    """:func:`clearance`'s distances for a walkable mask with cells of ``res`` m."""
    if free.all():
        return np.full(free.shape, np.inf)
    return ndimage.distance_transform_edt(free) * res - 0.5 * res


def traversable(grid: NavGrid, agent_radius: float, unknown: str = "interior") -> np.ndarray:
    """(H, W) bool: walkable cells farther than ``agent_radius`` (m) from every blocked cell
    (see :func:`clearance`)."""
    free, dist = clearance(grid, unknown)
    return free & (dist > float(agent_radius))


@dataclass
class CellGraph:
    """8-connected graph of traversable cells: ``mask`` (H,W), ``index`` (H,W) node of each
    cell (-1: none), ``cells`` (n,2) row/col of each node, ``matrix`` edge lengths in cells;
    ``preferred`` (H,W): the cells with the full clearance (None: all of ``mask``)."""

    mask: np.ndarray
    index: np.ndarray
    cells: np.ndarray
    matrix: csr_matrix
    preferred: np.ndarray | None = None


def build_graph(mask: np.ndarray, cost: np.ndarray | None = None) -> CellGraph:
    """The cell graph of a traversable mask; diagonal moves need both side cells traversable.
    ``cost`` (H, W): step length multiplier per cell (an edge costs the mean of its two ends)."""
    H, W = mask.shape
    index = np.full((H, W), -1, np.int64)
    cells = np.argwhere(mask)
    index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    src, dst, w = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = mask[max(0, -dr) : H - max(0, dr), max(0, -dc) : W - max(0, dc)]
        r0, c0 = max(0, -dr), max(0, -dc)
        sh = (slice(r0 + dr, r0 + dr + a.shape[0]), slice(c0 + dc, c0 + dc + a.shape[1]))
        both = a & mask[sh]
        if dr and dc:  # no corner cutting
            both &= mask[r0 + dr : r0 + dr + a.shape[0], c0 : c0 + a.shape[1]]
            both &= mask[r0 : r0 + a.shape[0], c0 + dc : c0 + dc + a.shape[1]]
        rr, cc = np.nonzero(both)
        i = index[rr + r0, cc + c0]
        j = index[rr + r0 + dr, cc + c0 + dc]
        step = np.full(len(i), float(np.hypot(dr, dc)))
        if cost is not None:
            step *= 0.5 * (cost[rr + r0, cc + c0] + cost[rr + r0 + dr, cc + c0 + dc])
        src += [i, j]
        dst += [j, i]
        w.append(np.concatenate([step, step]))
    n = len(cells)
    matrix = csr_matrix((np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(n, n))
    return CellGraph(mask, index, cells, matrix)


def _cell_of(grid: NavGrid, xy: np.ndarray) -> np.ndarray:
    return np.floor((np.asarray(xy, dtype=np.float64) - grid.origin) / grid.resolution).astype(np.int64)[::-1]


def _center(grid: NavGrid, rc: np.ndarray) -> np.ndarray:
    rc = np.asarray(rc)
    return grid.origin + (rc[..., ::-1] + 0.5) * grid.resolution


def _snap(g: CellGraph, rc: np.ndarray, max_cells: float) -> np.ndarray | None:
    """``rc`` (row, col) where it is a node of the graph, else the nearest node within
    ``max_cells``, or None: a cell with the full clearance where there is one in reach."""
    H, W = g.mask.shape
    if 0 <= rc[0] < H and 0 <= rc[1] < W and g.mask[rc[0], rc[1]]:
        return rc
    if len(g.cells) == 0:
        return None
    d = np.hypot(*(g.cells - rc).T)
    if g.preferred is not None:
        pref = g.preferred[g.cells[:, 0], g.cells[:, 1]]
        if pref.any() and d[pref].min() <= max_cells:
            d = np.where(pref, d, np.inf)
    k = int(np.argmin(d))
    return g.cells[k] if d[k] <= max_cells else None


def visible(mask: np.ndarray, a: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(J,) bool: do all cells on the segment from cell ``a`` (row, col) to each of ``targets``
    (J,2) lie in ``mask``? Samples every quarter cell, on the segment and a quarter cell
    diagonally off it, so a segment cannot slip between two diagonal blocked cells."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    if len(b) == 0:
        return np.zeros(0, dtype=bool)
    n = (np.ceil(4.0 * np.max(np.abs(b - a), axis=1)).astype(np.int64) + 1).clip(min=2)
    seg = np.repeat(np.arange(len(b)), n)
    start = np.cumsum(n) - n
    t = (np.arange(int(n.sum())) - start[seg]) / (n[seg] - 1)
    p = a[None] + t[:, None] * (b[seg] - a[None])
    H, W = mask.shape
    ok = np.ones(len(p), dtype=bool)
    for dr, dc in ((0.0, 0.0), (0.25, 0.25), (0.25, -0.25), (-0.25, 0.25), (-0.25, -0.25)):
        rr = np.floor(p[:, 0] + dr + 0.5).astype(np.int64)
        cc = np.floor(p[:, 1] + dc + 0.5).astype(np.int64)
        inside = (rr >= 0) & (cc >= 0) & (rr < H) & (cc < W)
        ok &= inside & mask[rr.clip(0, H - 1), cc.clip(0, W - 1)]
    blocked = np.add.reduceat((~ok).astype(np.int64), start)
    return blocked == 0


def smooth(mask: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Greedy line-of-sight shortening of a cell path (k,2): from each kept cell jump to the
    farthest later turning cell (or the end) in sight. Straight runs between turns add no
    shortcut, so only turning cells are candidates."""
    if len(cells) <= 2:
        return cells
    step = np.diff(cells, axis=0)
    turns = np.nonzero(np.any(step[1:] != step[:-1], axis=1))[0] + 1
    key = np.concatenate([[0], turns, [len(cells) - 1]])
    out = [0]
    i = 0
    while i < len(key) - 1:
        vis = visible(mask, cells[key[i]], cells[key[i + 1 :]])
        j = i + 1 + int(np.nonzero(vis)[0].max()) if vis.any() else i + 1
        out.append(j)
        i = j
    return cells[key[out]]


def plan_on_graph(grid: NavGrid, g: CellGraph, start_xy: np.ndarray, goal_xy: np.ndarray,
                  snap_distance: float) -> list[tuple[float, float]] | None:
    """Shortest smoothed path on a prebuilt graph; start/goal snap to the nearest traversable
    cell within ``snap_distance`` (m). Returns world (x, y) waypoints or None."""
    s_xy = np.asarray(start_xy, dtype=np.float64).reshape(2)
    g_xy = np.asarray(goal_xy, dtype=np.float64).reshape(2)
    if not (np.all(np.isfinite(s_xy)) and np.all(np.isfinite(g_xy))):
        raise ValueError("start and goal must be finite (x, y) in metres")
    max_cells = snap_distance / grid.resolution
    s = _snap(g, _cell_of(grid, s_xy), max_cells)
    t = _snap(g, _cell_of(grid, g_xy), max_cells)
    if s is None or t is None:
        return None
    si, ti = int(g.index[s[0], s[1]]), int(g.index[t[0], t[1]])
    if si == ti:
        path_idx = [si]
    else:
        # the matrix holds both directions of every edge
        dist, pred = dijkstra(g.matrix, directed=True, indices=si, return_predecessors=True)
        if not np.isfinite(dist[ti]):
            return None
        path_idx = [ti]
        while path_idx[-1] != si:
            path_idx.append(int(pred[path_idx[-1]]))
        path_idx.reverse()
    cells = g.cells[path_idx]
    if g.preferred is None:
        cells = smooth(g.mask, cells)
    else:  # shortcuts may not cut into squeezed cells the path does not already use
        sight = g.preferred.copy()
        sight[cells[:, 0], cells[:, 1]] = True
        cells = smooth(sight, cells)
    pts = _center(grid, cells)
    # keep the exact start / goal when they lie in their (traversable) cells
    if np.array_equal(s, _cell_of(grid, s_xy)):
        pts[0] = s_xy
    if np.array_equal(t, _cell_of(grid, g_xy)):
        pts[-1] = g_xy
    if len(pts) == 1:
        pts = np.vstack([pts, pts[-1:]])
    return [(float(x), float(y)) for x, y in pts]


def nav_graph(grid: NavGrid, agent_radius: float, unknown: str = "interior", base: NavGrid | None = None,
              squeeze: float = SQUEEZE) -> CellGraph:
    """The navigation graph of a grid for a disc of ``agent_radius`` m: the cells with the
    full clearance in ``grid``, plus (at :data:`SQUEEZE_COST`) those ``squeeze`` m closer to
    the obstacles of ``base`` (the grid without margins or doubtful tracks; default ``grid``)."""
    if not (np.isfinite(squeeze) and squeeze >= 0.0):
        raise ValueError(f"squeeze={squeeze} must be finite and >= 0 (metres)")
    free, cost = walkable(grid, unknown)
    dist = _distance(free, float(grid.resolution))
    preferred = free & (dist > float(agent_radius))
    allowed = preferred
    if squeeze > 0.0:
        if base is not None and base is not grid:  # the margins left out
            free, cost = walkable(base, unknown)
            allowed = preferred | (free & (_distance(free, float(base.resolution)) > agent_radius - squeeze))
        else:
            allowed = preferred | (free & (dist > agent_radius - squeeze))
    cost = np.where(preferred, cost, SQUEEZE_COST * cost)
    if COMFORT > 0:
        band = preferred & (dist <= agent_radius + COMFORT)
        cost = np.where(band, cost * (1 + COMFORT_COST * (agent_radius + COMFORT - dist) / COMFORT), cost)
    g = build_graph(allowed, cost)
    if squeeze > 0.0:
        g.preferred = preferred
    return g


def default_snap(agent_radius: float) -> float:
    """How far (m) a start or goal inside the inflated (and padded) obstacles may move to the
    nearest traversable cell by default: the radius plus :data:`SNAP_EXTRA`, since the boxes
    the grid is built from are often a few centimetres too large (a goal tolerance, as in
    nav2's planners)."""
    return float(agent_radius) + SNAP_EXTRA


def planning_grids(scene_or_grid: Any, uncertainty: float = UNCERTAINTY) -> tuple[NavGrid, NavGrid]:
    """``(padded, base)``: the grid plans keep the full clearance on (a scene's grid with the
    margins of :mod:`.margins` around its objects) and the grid a squeeze may use (the scene's
    grid without its doubtful tracks, :func:`.margins.without_doubtful`; a bare grid: both)."""
    if isinstance(scene_or_grid, NavGrid) or hasattr(scene_or_grid, "resolution"):
        grid = as_grid(scene_or_grid)
        return grid, grid
    scene = load_scene(scene_or_grid)
    if scene.grid is None:
        raise ValueError("the scene has no navigation grid")
    return padded_grid(scene.grid, scene.objects, uncertainty), without_doubtful(scene.grid, scene.objects)


def plan(scene_or_grid: Any, start_xy: np.ndarray, goal_xy: np.ndarray, agent_radius: float = 0.2,
         unknown: str = "interior", snap_distance: float | None = None,
         uncertainty: float = UNCERTAINTY, squeeze: float = SQUEEZE) -> list[tuple[float, float]] | None:
    """Shortest path (world (x, y) waypoints, metres) for a disc of ``agent_radius`` from
    ``start_xy`` to ``goal_xy`` on the grid of a scene (or a ``NavGrid``-like grid); None when
    no path exists; ``unknown``: what unknown cells mean (module doc); ``uncertainty``:
    standard deviations of each box face's spread kept as extra distance (:mod:`.margins`;
    0 = none); ``squeeze``: how much closer (m) a plan may pass where nothing else gets
    through (module doc; 0 = never). ``snap_distance`` (default :func:`default_snap`) lets a
    start or goal inside the inflated margin move to the nearest traversable cell. Builds the
    graph on every call: use ``SceneQueries.plan`` to reuse it."""
    if not np.isfinite(agent_radius) or agent_radius < 0:
        raise ValueError(f"agent_radius={agent_radius} must be finite and >= 0 (metres)")
    padded, grid = planning_grids(scene_or_grid, uncertainty)
    g = nav_graph(padded, agent_radius, unknown, grid, squeeze)
    snap = default_snap(agent_radius) if snap_distance is None else float(snap_distance)
    return plan_on_graph(grid, g, start_xy, goal_xy, snap)
