"""Gravity (``up``) from a single depth frame, pure numpy + cv2 (no scipy).

The frame is reduced to a strided grid (:class:`DepthGrid`, ``stride`` x ``stride``
pixel blocks, shared with the geometric proposer) with block-mean points for plane
fitting and per-block normals (central differences over +-2 blocks, 3x3 smoothed);
gravity uses every 2nd row and column of it. Then, in order of preference:

1. **floor** -- up to three separated modes of the roughly horizontal (axial) normals
   within ``max_tilt_deg`` of the prior (a gnomonic histogram, then an axial mean in
   shrinking cones) are candidate axes; axes without Manhattan support (few surfaces
   parallel or perpendicular to them) are dropped. Along a candidate, the heights of
   up-facing points form a histogram whose *lowest* peak below the camera that is
   large, flat (curvature test), wide and has (almost) nothing under it is the floor --
   this also rejects a wall that outnumbers the floor when the camera looks steeply down
   (the wall has no "floor" under its axis). A weighted least-squares fit of the floor's
   band gives ``up`` and the floor plane; a small / thin floor patch uses one joint fit of
   all horizontal planes (or the normal mode when they are small too).
2. **horizontal** -- no floor, but other flat horizontal surfaces (table tops, seats,
   ceiling): the joint fit of all their planes (one normal, one offset per plane) or the
   normal mode.
3. **walls** -- no horizontal surface: two roughly orthogonal vertical plane families
   (Manhattan walls) give ``up`` as their cross product, refined by all wall normals; a
   single family only constrains it (the prior projected onto the wall plane).
4. **prior** -- nothing usable (no flat surface at all): the prior (default a level
   camera, ``(0, -1, 0)``) with confidence 0.

Frames: camera optical frame (x right, y down, z forward), metres; ``up`` is the
gravity-up unit vector in that frame. The floor plane is ``up . p + d = 0`` (``d`` is
the camera's height above the floor), so a point's height above the floor is
``up . p + d``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .geometry import DEFAULT_UP, normalize, upright_rotation
from .gravity_grid import _REF_POINTS, DepthGrid, auto_stride, make_grid
from .gravity_planes import (
    _axial_mean, _azimuth_mode, _curvature, _extent, _fit_band, _height_peaks, _joint_or_mode, _mode_directions,
    _plane_support, _plane_tol,
)

__all__ = ["SOURCES", "DepthGrid", "GravityConfig", "GravityEstimate", "auto_stride", "estimate_floor_along",
           "estimate_up", "gravity_with_floor", "make_grid"]

SOURCES = ("floor", "horizontal", "walls", "prior")


@dataclass
class GravityEstimate:
    """Estimated gravity-up vector (camera frame, unit) with its confidence in [0, 1].

    ``source``: 'floor' | 'horizontal' | 'walls' | 'prior'. ``floor_height``: the
    camera's height above the floor plane (m) when a floor was found, else None;
    ``plane``: that floor as ``(a, b, c, d)`` with ``(a, b, c) = up`` and
    ``up . p + d = 0`` on the floor (None without a floor). ``inliers``: number of grid
    points supporting the estimate; ``ceiling_height``: height of a ceiling plane above
    the floor (or above the camera when there is no floor) if one was seen.
    """

    up: np.ndarray
    confidence: float
    source: str
    floor_height: float | None = None
    plane: np.ndarray | None = None
    inliers: int = 0
    ceiling_height: float | None = None

    def height_above_floor(self, points: np.ndarray) -> np.ndarray | None:
        """Heights (N,) of camera-frame points above the floor, or None without a floor."""
        if self.plane is None:
            return None
        return np.asarray(points) @ self.plane[:3] + self.plane[3]


@dataclass
class GravityConfig:
    """Thresholds of :func:`estimate_up` (grid points are ``stride`` x ``stride`` blocks)."""

    stride: int | None = None  # None: auto_stride (VGA -> 4)
    max_depth: float = 10.0
    max_tilt_deg: float = 60.0  # how far ``up`` may be from the prior
    min_floor_frac: float = 0.01  # floor support, share of valid grid points
    min_floor_points: int = 60
    min_floor_extent: float = 0.15  # m, smaller in-plane extent of the floor inliers
    min_floor_length: float = 0.4  # m, larger in-plane extent
    min_floor_below: float = 0.15  # m, floor at least this far below the camera
    max_below_frac: float = 0.01  # share of points allowed clearly below the floor
    min_plane_points: int = 40  # any horizontal plane
    min_wall_points: int = 80
    max_curvature: float = 0.2  # 1/m: planes are flat (a 5 m radius is still 'flat')


def estimate_up(
    depth: np.ndarray | None,
    K: np.ndarray,
    prior_up: np.ndarray | None = None,
    stride: int | None = None,
    config: GravityConfig | None = None,
    grid: DepthGrid | None = None,
) -> GravityEstimate:
    """Gravity-up unit vector in the camera frame from a depth map (m, NaN invalid).

    ``prior_up``: expected up (default a level camera, ``(0, -1, 0)``), used to pick the
    horizontal direction, orient the result and as the fallback (confidence 0) when
    the scene shows no usable plane. ``grid``: a :class:`DepthGrid` already made from
    this frame (then ``depth`` and ``stride`` are ignored); ``stride`` None: the
    config's, else :func:`auto_stride` (VGA -> 4).
    """
    cfg = config or GravityConfig()
    if grid is None:
        grid = make_grid(depth, K, stride=stride or cfg.stride, max_depth=cfg.max_depth)
    u0 = normalize(DEFAULT_UP if prior_up is None else np.asarray(prior_up, np.float64).reshape(3))
    fallback = GravityEstimate(u0.copy(), 0.0, "prior")
    # point-count thresholds are for a VGA frame at stride 4: scale them to this grid
    k = grid.valid.size / _REF_POINTS
    if abs(k - 1.0) > 0.05:
        cfg = replace(
            cfg,
            min_floor_points=max(8, int(round(cfg.min_floor_points * k))),
            min_plane_points=max(6, int(round(cfg.min_plane_points * k))),
            min_wall_points=max(10, int(round(cfg.min_wall_points * k))),
        )

    # every 2nd row and column of the grid is plenty for gravity (point counts x 4)
    sub = (slice(None, None, 2), slice(None, None, 2)) if grid.valid.size >= 4 * 4800 else (slice(None), slice(None))
    f = 4 if sub[0].step else 1
    nmask = grid.nvalid[sub]
    # float64 once: every product with a float64 axis below would convert them again
    N = grid.normals[sub][nmask].astype(np.float64)
    if N.shape[0] * f < 30:
        return fallback
    P = grid.pmean[sub][nmask].astype(np.float64)
    n_valid = int(np.count_nonzero(grid.valid))
    Ns = N
    Pc = grid.points[sub][grid.valid[sub]].astype(np.float64)
    if f > 1:  # thresholds in full-grid points -> this subsample
        cfg = replace(
            cfg,
            min_floor_points=max(4, cfg.min_floor_points // f),
            min_plane_points=max(4, cfg.min_plane_points // f),
            min_wall_points=max(6, cfg.min_wall_points // f),
        )
        n_valid = max(1, n_valid // f)

    # 1. densest axes of (near-)horizontal normals within max_tilt of the prior: the floor,
    # table tops, the ceiling -- or a wall when the camera is steeply tilted, so try the
    # next modes too and prefer one under which a floor is found.
    best: tuple[float, GravityEstimate] | None = None
    cands = _candidate_axes(Ns, u0, cfg)
    m_best = max((m for _, m in cands), default=0)
    for u1, m in cands:
        if m < 0.5 * m_best:  # not a Manhattan axis (a slanted surface)
            continue
        est = _from_horizontal(N, P, Pc, u1, u0, n_valid, cfg)
        if est is None:
            continue
        if est.source == "floor":
            return est
        # no floor: prefer axes with surfaces seen from above (tops) over only ceiling-like ones
        score = est.inliers
        if best is None or score > best[0]:
            best = (score, est)
    if best is not None:
        return best[1]
    est = _from_walls(N, P, u0, cfg)
    return est if est is not None else fallback


def _candidate_axes(Ns: np.ndarray, u0: np.ndarray, cfg: GravityConfig) -> list[tuple[np.ndarray, int]]:
    """Up to 3 densest axes of the normals ``Ns`` (camera frame) within ``max_tilt_deg`` of the
    prior ``u0``, each oriented along ``u0``, with its Manhattan support (normals parallel or
    perpendicular to it)."""
    cands = []
    for u1, _peak in _mode_directions(Ns, u0, cfg.max_tilt_deg, k=3):
        u1, cnt = _axial_mean(Ns, u1)
        if u1 @ u0 < 0:
            u1 = -u1
        if cnt < cfg.min_plane_points or u1 @ u0 < np.cos(np.radians(cfg.max_tilt_deg)):
            continue
        # Manhattan support: surfaces parallel or perpendicular to the axis
        c = np.abs(Ns @ u1)
        cands.append((u1, int(np.count_nonzero(c > 0.99)) + int(np.count_nonzero(c < 0.14))))
    return cands


def _find_floor(peaks_up, Pu, Nu, Pc, hc, tol_c, u1, min_floor: int, max_below: int,
                cfg: GravityConfig) -> tuple[float, int, float, float] | None:
    """The floor along ``u1``: the lowest well-supported up-facing plane below the camera with
    (almost) nothing under it, as ``(height (m along u1), points on it, extent 1, extent 2 (m))``;
    support counts all points ``Pc`` on it (floors are often speckled, with few normals)."""
    for h0, _cnt in peaks_up:
        if h0 > -cfg.min_floor_below:
            break
        on = np.abs(hc - h0) < tol_c
        nin = int(on.sum())
        if nin < min_floor:
            continue
        bu = np.abs(Pu @ u1 - h0) < _plane_tol(Pu[:, 2])
        if bu.sum() >= 10 and abs(_curvature(Pu[bu], Nu[bu], u1)) > cfg.max_curvature:
            continue  # a curved surface, not a floor
        e1, e2 = _extent(Pc[on][:: max(1, nin // 3000)], u1)
        if e2 < cfg.min_floor_extent or e1 < cfg.min_floor_length:
            continue
        if int(np.count_nonzero(hc < h0 - 0.1 - 2 * tol_c)) > max_below:
            continue
        return (h0, nin, e1, e2)
    return None


def _find_ceiling(peaks_dn, Pc, hc, tol_c, u1, min_floor: int, max_below: int) -> float | None:
    """Height (m along ``u1``) of the highest down-facing plane at least 0.3 m above the camera,
    0.5 m or more across, with (almost) nothing above it; None without one."""
    for h0, _cnt in reversed(peaks_dn):
        if h0 < 0.3:
            break
        on = np.abs(hc - h0) < tol_c
        if on.sum() < min_floor:
            continue
        e1, e2 = _extent(Pc[on][:: max(1, int(on.sum()) // 1500)], u1)
        if e2 >= 0.5 and int(np.count_nonzero(hc > h0 + 0.1 + 2 * tol_c)) <= max_below:
            return h0
    return None


def _from_horizontal(N, P, Pc, u1, u0, n_valid, cfg: GravityConfig) -> GravityEstimate | None:
    """Floor (or, without one, all horizontal planes) along the candidate axis ``u1``."""
    cos_h = np.cos(np.radians(20.0))
    c = N @ u1
    upf = c > cos_h  # horizontal, facing up (seen from above: floor, table tops)
    dnf = c < -cos_h  # facing down (ceiling, undersides)
    Pu, Pd = P[upf], P[dnf]
    Nu, Nd = N[upf], N[dnf]
    min_floor = max(cfg.min_floor_points, int(cfg.min_floor_frac * n_valid))
    peaks_up = _height_peaks(Pu @ u1, 0.03, cfg.min_plane_points)
    peaks_dn = _height_peaks(Pd @ u1, 0.03, cfg.min_plane_points)
    tol_c = _plane_tol(Pc[:, 2])
    max_below = max(10, int(cfg.max_below_frac * n_valid))
    hc = Pc @ u1
    floor = _find_floor(peaks_up, Pu, Nu, Pc, hc, tol_c, u1, min_floor, max_below, cfg)
    ceiling = _find_ceiling(peaks_dn, Pc, hc, tol_c, u1, min_floor, max_below)
    if floor is not None:
        h0, nin, e1, e2 = floor
        un, hh, sel = _fit_band(Pu, u1, h0)
        big = nin >= 0.03 * n_valid and e2 >= 1.0 and sel.sum() >= 200
        if not big or un @ u1 < np.cos(np.radians(5)):
            # small / thin floor patch: one joint fit of all horizontal planes (table tops,
            # seats, ceiling) selected along the (many-normal) mode axis
            groups = []
            for peaks, Q in ((peaks_up, Pu), (peaks_dn, Pd)):
                hq = Q @ u1
                tq = _plane_tol(Q[:, 2])
                for hp, _cnt in peaks:
                    sel_p = np.abs(hq - hp) < tq
                    if sel_p.sum() >= cfg.min_plane_points or (Q is Pu and hp == h0 and sel_p.sum() >= 10):
                        groups.append(Q[sel_p])
            un = _joint_or_mode(groups, u1, n_valid, 5.0)
            on = np.abs(hc - h0) < tol_c
            hh = float(np.median(Pc[on] @ un))
        up = normalize(un)
        conf = float(np.clip(0.5 + 0.25 * min(1.0, nin / (0.1 * n_valid)) + 0.25 * min(1.0, e2 / 2.0), 0, 1))
        ch = None if ceiling is None else float(ceiling - h0)
        return GravityEstimate(
            up, conf, "floor", floor_height=float(-hh), plane=np.array([*up, -hh]), inliers=nin, ceiling_height=ch
        )
    # 2. no floor: one joint fit over all horizontal planes (up- and down-facing)
    groups = []
    total = 0.0
    for peaks, Q, NQ, wgt in ((peaks_up, Pu, Nu, 1.0), (peaks_dn, Pd, Nd, 0.25)):
        for h0, _cnt in peaks:
            sel = np.abs(Q @ u1 - h0) < _plane_tol(Q[:, 2])
            if sel.sum() >= cfg.min_plane_points and abs(_curvature(Q[sel], NQ[sel], u1)) < cfg.max_curvature:
                groups.append(Q[sel])
                total += wgt * int(sel.sum())
    if not groups:
        return None
    uj = _joint_or_mode(groups, u1, n_valid, 8.0)
    if uj @ u0 < 0:
        uj = -uj
    span = max(_extent(g, uj)[0] for g in groups)
    if span < 0.3:
        return None
    conf = float(np.clip(0.2 + 0.2 * min(1.0, total / (0.1 * n_valid)) + 0.2 * min(1.0, span / 1.5), 0, 0.6))
    ch = None if ceiling is None else float(ceiling)
    return GravityEstimate(normalize(uj), conf, "horizontal", inliers=int(total), ceiling_height=ch)


def _from_walls(N: np.ndarray, P: np.ndarray, u0: np.ndarray, cfg: GravityConfig) -> GravityEstimate | None:
    """Up from vertical (wall) normals: two orthogonal wall families, or one (constraint only)."""
    tilt = np.sin(np.radians(min(cfg.max_tilt_deg, 45.0)))
    vmask = np.abs(N @ u0) < tilt
    V, PV = N[vmask], P[vmask]
    if len(V) < cfg.min_wall_points:
        return None
    R = upright_rotation(u0)
    d1, c1 = _azimuth_mode(V, R)
    if c1 < cfg.min_wall_points:
        return None
    d1, c1 = _axial_mean(V, d1, (25.0, 12.0, 6.0))
    fam1 = np.abs(V @ d1) > np.cos(np.radians(8))
    if _plane_support(PV[fam1], d1) < cfg.min_wall_points or _extent(PV[fam1], d1)[1] < 0.4:
        return None
    orth = np.abs(V @ d1) < np.sin(np.radians(25))
    V2, P2 = V[orth], PV[orth]
    if len(V2) >= cfg.min_wall_points:
        d2, c2 = _azimuth_mode(V2, R)
        d2, c2 = _axial_mean(V2, d2, (25.0, 12.0, 6.0))
        fam2 = np.abs(V2 @ d2) > np.cos(np.radians(8))
        if (
            c2 >= cfg.min_wall_points
            and abs(d1 @ d2) < np.sin(np.radians(12))
            and _plane_support(P2[fam2], d2) >= cfg.min_wall_points
            and _extent(P2[fam2], d2)[1] >= 0.4
        ):
            up = normalize(np.cross(d1, d2))
            for _ in range(3):  # refine: up is the direction most orthogonal to all wall normals
                W = V[np.abs(V @ up) < np.sin(np.radians(8))]
                if len(W) < cfg.min_wall_points:
                    break
                _, vecs = np.linalg.eigh(W.T @ W)
                nu = vecs[:, 0]
                up = nu if nu @ up > 0 else -nu
            if up @ u0 < 0:
                up = -up
            if up @ u0 > np.cos(np.radians(cfg.max_tilt_deg)):
                conf = float(np.clip(0.15 + 0.25 * min(1.0, min(c1, c2) / 500.0), 0, 0.4))
                return GravityEstimate(up, conf, "walls", inliers=int(c1 + c2))
    # one family: the prior projected onto the wall plane
    up = normalize(u0 - (u0 @ d1) * d1)
    return GravityEstimate(up, 0.1, "walls", inliers=int(c1))


def estimate_floor_along(grid: DepthGrid, K: np.ndarray, up: np.ndarray, gcfg: GravityConfig | None = None) -> GravityEstimate:
    """A known ``up`` (camera frame; source 'prior', confidence 1) with the floor plane
    (``floor_height``, m below the camera) measured along it when a floor is seen."""
    up = up / np.linalg.norm(up)
    est = estimate_up(None, K, prior_up=up, grid=grid, config=gcfg or GravityConfig())
    out = GravityEstimate(up.copy(), 1.0, "prior", inliers=est.inliers)
    if est.plane is not None and float(est.up @ up) > np.cos(np.radians(5.0)):
        P = grid.pmean[grid.nvalid].astype(np.float64)
        hh = P @ est.plane[:3] + est.plane[3]
        near = np.abs(hh) < 0.05
        if near.sum() >= 10:
            d = -float(np.median(P[near] @ up))
            out.floor_height = d
            out.plane = np.array([*up, d])
            if est.ceiling_height is not None:
                out.ceiling_height = est.ceiling_height
    return out


def gravity_with_floor(depth: np.ndarray, K: np.ndarray, up: np.ndarray | None = None) -> GravityEstimate:
    """Gravity for a frame: ``up`` (camera frame) when given, with the floor measured along
    it (:func:`estimate_floor_along`); else estimated from the depth (:func:`estimate_up`)."""
    if up is None:
        return estimate_up(depth, K)
    K = np.asarray(K, np.float64)
    return estimate_floor_along(make_grid(depth, K, stride=auto_stride(np.shape(depth))), K, np.asarray(up, np.float64))
