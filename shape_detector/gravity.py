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

import cv2
import numpy as np

from .geometry import DEFAULT_UP, normalize, upright_rotation

SOURCES = ("floor", "horizontal", "walls", "prior")
_REF_POINTS = 160 * 120  # point-count thresholds are for a VGA frame at stride 4
_NORMAL_K = (2, 0)  # central-difference half-baselines in cells: near, far (beyond 2.5 m; 0: off)


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
class DepthGrid:
    """A depth frame reduced to ``stride`` x ``stride`` pixel blocks (camera frame, metres).

    ``points`` (h,w,3) float32: per block a real surface point for clustering (the block
    mean on smooth blocks, the nearest valid sample on blocks spanning a depth edge, so
    no "flying" points between objects); NaN where invalid. ``pmean`` (h,w,3): block-mean
    points (noise-reduced, NaN on edge or empty blocks) for plane fitting. ``normals``
    (h,w,3): smoothed unit normals facing the camera (0 where unknown or where the
    3x3 neighbourhood disagrees, e.g. on creases), ``nvalid`` their mask; ``rnormals`` /
    ``rvalid``: the same smoothed normals without the agreement test (also defined on
    creases; valid where most of the 3x3 neighbourhood has raw normals).
    ``u``/``v``: pixel-centre coordinates of the block centres (columns (w,), rows (h,)).
    """

    stride: int
    points: np.ndarray
    valid: np.ndarray
    pmean: np.ndarray
    normals: np.ndarray
    nvalid: np.ndarray
    u: np.ndarray
    v: np.ndarray
    image_shape: tuple[int, int]
    rnormals: np.ndarray | None = None
    rvalid: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape  # type: ignore[return-value]


def auto_stride(shape: tuple[int, ...]) -> int:
    """Grid stride giving about 160 x 120 blocks for an image of ``shape`` (VGA -> 4)."""
    return max(1, int(round(np.sqrt(shape[0] * shape[1] / _REF_POINTS))))


def make_grid(depth: np.ndarray, K: np.ndarray, stride: int | None = 4, max_depth: float = 10.0) -> DepthGrid:
    """Strided back-projection of ``depth`` (HxW float32 m, NaN/0 invalid) with normals
    (``stride`` None: :func:`auto_stride`)."""
    depth = np.asarray(depth)
    H, W = depth.shape
    s = auto_stride((H, W)) if not stride else max(1, int(stride))
    h, w = H // s, W // s
    dc = np.array(depth[: h * s, : w * s], dtype=np.float32, order="C")  # copy
    cv2.patchNaNs(dc, 0.0)
    cv2.threshold(dc, float(max_depth), 0.0, cv2.THRESH_TOZERO_INV, dst=dc)
    cv2.threshold(dc, 0.0, 0.0, cv2.THRESH_TOZERO, dst=dc)  # negatives / inf -> 0
    okf = cv2.threshold(dc, 0.0, 1.0, cv2.THRESH_BINARY)[1]
    if s > 1:
        area = cv2.INTER_AREA
        frac = cv2.resize(okf, (w, h), interpolation=area)
        msum = cv2.resize(dc, (w, h), interpolation=area)
        alt = cv2.addWeighted(dc, 1.0, okf, -1e4, 1e4)  # invalid -> 1e4
        dmin = _block_reduce(alt, s, np.minimum)
        dmax = _block_reduce(dc, s, np.maximum)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = msum / frac
    else:
        frac = okf
        mean = dmin = dmax = dc
    bvalid = frac > 0.5 / (s * s)  # at least one valid pixel (floors are often speckled)
    edge = (dmax - dmin) > 0.03 + 0.04 * dmin  # block spans a depth discontinuity
    smooth = bvalid & ~edge
    zc = np.where(smooth, mean, dmin)
    zc = np.where(bvalid, zc, np.nan).astype(np.float32)
    zm = np.where(smooth, mean, np.nan).astype(np.float32)

    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    u = (np.arange(w, dtype=np.float32) * s + 0.5 * (s - 1)).astype(np.float32)
    v = (np.arange(h, dtype=np.float32) * s + 0.5 * (s - 1)).astype(np.float32)
    ru = ((u - cx) / fx)[None, :]
    rv = ((v - cy) / fy)[:, None]
    pts = np.stack([ru * zc, rv * zc, zc], axis=-1)
    pm = np.stack([ru * zm, rv * zm, zm], axis=-1)
    msm = smooth & bvalid
    Z = np.where(msm, mean, 0.0).astype(np.float32)
    X, Y = ru * Z, rv * Z

    normals = np.zeros((h, w, 3), np.float32)
    nvalid = np.zeros((h, w), bool)
    rnormals = np.zeros((h, w, 3), np.float32)
    rvalid = np.zeros((h, w), bool)
    if h >= 2 * _NORMAL_K[0] + 1 and w >= 2 * _NORMAL_K[0] + 1:
        n1, g1 = _raw_normals(X, Y, Z, msm, _NORMAL_K[0])
        if _NORMAL_K[1] and h >= 7 and w >= 7:
            # far away the depth noise swamps short baselines: 3-block differences there
            n3_, g3 = _raw_normals(X, Y, Z, msm, _NORMAL_K[1])
            far = g3 & (Z > 2.5)
            nraw = np.where(far[..., None], n3_, n1)
            good = far | (g1 & ~(Z > 2.5)) | (g1 & ~g3)
        else:
            nraw, good = n1, g1
        # smooth (3x3 mean of unit normals); keep normals whose neighbourhood agrees
        nb = cv2.blur(nraw, (3, 3), borderType=cv2.BORDER_CONSTANT)
        gcount = cv2.blur(good.astype(np.float32), (3, 3), borderType=cv2.BORDER_CONSTANT)
        ln = np.sqrt(cv2.transform(cv2.multiply(nb, nb), np.ones((1, 3), np.float32)))
        keep = good & (ln > 0.85 * gcount) & (gcount > 0.5)
        keep[0, :] = keep[-1, :] = False
        keep[:, 0] = keep[:, -1] = False
        unit = nb / np.maximum(ln, 1e-12)[..., None]
        normals[:] = unit * keep[..., None]
        nvalid[:] = keep
        rnormals[:] = unit
        rvalid[:] = gcount > 0.6
    return DepthGrid(s, pts, bvalid, pm, normals, nvalid, u, v, (H, W), rnormals, rvalid)


def _block_reduce(a: np.ndarray, s: int, op) -> np.ndarray:
    """``op`` (np.minimum / np.maximum) over each ``s`` x ``s`` block of ``a`` (shape divisible)."""
    r = a[0::s]
    for i in range(1, s):
        r = op(r, a[i::s])
    c = r[:, 0::s]
    for j in range(1, s):
        c = op(c, r[:, j::s])
    return c


def _raw_normals(X: np.ndarray, Y: np.ndarray, Z: np.ndarray, m: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (h,w,3) facing the camera from central differences over +-``k`` cells
    (0 at the border, at invalid cells and across depth discontinuities) and their mask.
    ``X, Y, Z``: block-mean points with 0 where ``m`` (valid) is False."""
    h, w = Z.shape
    c = (slice(k, h - k), slice(k, w - k))
    L, Rt = (slice(k, h - k), slice(0, w - 2 * k)), (slice(k, h - k), slice(2 * k, w))
    U, D = (slice(0, h - 2 * k), slice(k, w - k)), (slice(2 * k, h), slice(k, w - k))
    ax, ay, az = X[Rt] - X[L], Y[Rt] - Y[L], Z[Rt] - Z[L]
    bx, by, bz = X[D] - X[U], Y[D] - Y[U], Z[D] - Z[U]
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    zi = Z[c]
    lim = k * (0.6 * zi + 0.2)
    nrm = np.sqrt(nx * nx + ny * ny + nz * nz)
    gi = m[c] & m[L] & m[Rt] & m[U] & m[D] & (np.abs(az) < lim) & (np.abs(bz) < lim) & (nrm > 1e-12)
    facing = nx * X[c] + ny * Y[c] + nz * zi  # orient towards the camera (n . p < 0)
    inv = gi / np.maximum(nrm, 1e-12)
    scale = np.where(facing > 0, -inv, inv).astype(np.float32)
    out = np.zeros((h, w, 3), np.float32)
    good = np.zeros((h, w), bool)
    out[c] = np.stack([nx * scale, ny * scale, nz * scale], axis=-1)
    good[c] = gi
    return out, good


# ---------------------------------------------------------------------------------------


def _fit_planes_joint(groups: list[np.ndarray], weights: list[np.ndarray] | None = None) -> np.ndarray:
    """Common unit normal of several parallel planes (each group (N_k,3) of its points)."""
    C = np.zeros((3, 3))
    for i, g in enumerate(groups):
        g = np.asarray(g, dtype=np.float64)
        wts = None if weights is None else weights[i]
        if wts is None:
            c = g.mean(axis=0)
            q = g - c
            C += q.T @ q
        else:
            c = (g * wts[:, None]).sum(0) / wts.sum()
            q = g - c
            C += (q * wts[:, None]).T @ q
    _, vecs = np.linalg.eigh(C)
    return vecs[:, 0]


def _mode_directions(
    n: np.ndarray, u0: np.ndarray, max_angle_deg: float, k: int = 3, bin_deg: float = 2.0, sep_deg: float = 20.0
) -> list[tuple[np.ndarray, int]]:
    """Up to ``k`` separated modes (direction, smoothed count) of the axial unit vectors ``n``
    within ``max_angle`` of ``u0`` (gnomonic histogram in the frame of ``u0``), densest first."""
    R = upright_rotation(u0)
    q = n @ R
    qz = q[:, 2]
    sgn = np.where(qz >= 0, 1.0, -1.0)
    qz = qz * sgn
    sel = qz > np.cos(np.radians(max_angle_deg))
    if not np.any(sel):
        return []
    a = q[sel, 0] * sgn[sel] / qz[sel]
    b = q[sel, 1] * sgn[sel] / qz[sel]
    lim = np.tan(np.radians(max_angle_deg))
    step = np.tan(np.radians(bin_deg))
    nb = int(np.ceil(2 * lim / step)) + 1
    ia = np.clip(((a + lim) / step).astype(np.int64), 0, nb - 1)
    ib = np.clip(((b + lim) / step).astype(np.int64), 0, nb - 1)
    hist = np.bincount(ib * nb + ia, minlength=nb * nb).reshape(nb, nb).astype(np.float32)
    hs = cv2.blur(hist, (3, 3), borderType=cv2.BORDER_CONSTANT) * 9
    out: list[tuple[np.ndarray, int]] = []
    cos_sep = np.cos(np.radians(sep_deg))
    r = max(1, int(round(sep_deg / bin_deg)))
    for _ in range(4 * k):
        j = int(np.argmax(hs))
        c = float(hs.flat[j])
        if c <= 0 or len(out) >= k:
            break
        jb, ja = divmod(j, nb)
        hs[max(jb - r, 0) : jb + r + 1, max(ja - r, 0) : ja + r + 1] = 0
        d = normalize(R @ np.array([(ja + 0.5) * step - lim, (jb + 0.5) * step - lim, 1.0]))
        if any(abs(d @ o[0]) > cos_sep for o in out):
            continue
        out.append((d, int(c)))
    return out


def _axial_mean(n: np.ndarray, u: np.ndarray, angles_deg=(10.0, 6.0, 4.0)) -> tuple[np.ndarray, int]:
    """Refine the axis ``u`` as the mean of the (sign-aligned) ``n`` in shrinking cones."""
    cnt = 0
    sub = n
    for i, ang in enumerate(angles_deg):
        c = sub @ u
        sel = np.abs(c) > np.cos(np.radians(ang))
        cnt = int(sel.sum())
        if cnt < 3:
            break
        sub, c = sub[sel], c[sel]
        u = normalize((sub * np.sign(c)[:, None]).sum(0))
        if i == 0:  # later cones only look at the first cone's members (+ margin)
            c = n @ u
            sub = n[np.abs(c) > np.cos(np.radians(ang + 3.0))]
    return u, cnt


def _height_peaks(h: np.ndarray, bin_m: float, min_count: int) -> list[tuple[float, int]]:
    """Local maxima (height, smoothed count) of a 1D histogram of ``h``, ascending height."""
    if h.size == 0:
        return []
    lo = float(h.min()) - 2 * bin_m
    nb = int((float(h.max()) - lo) / bin_m) + 3
    if nb > 20000:
        return []
    idx = ((h - lo) / bin_m).astype(np.int64)
    cnt = np.bincount(idx, minlength=nb).astype(np.float64)
    sm = cnt.copy()
    sm[1:] += cnt[:-1]
    sm[:-1] += cnt[1:]
    peaks = []
    for i in np.nonzero(sm >= min_count)[0]:
        left = sm[i - 1] if i > 0 else -1
        right = sm[i + 1] if i + 1 < nb else -1
        if sm[i] >= left and sm[i] > right:
            c = lo + (i + 0.5) * bin_m
            near = h[np.abs(h - c) < 1.5 * bin_m]
            c = float(np.median(near)) if near.size else c
            if peaks and abs(c - peaks[-1][0]) < bin_m:
                continue
            peaks.append((c, int(sm[i])))
    return peaks


def _plane_tol(z: np.ndarray) -> np.ndarray:
    """Inlier half-band (m) of a plane at range ``z``: grows with depth noise."""
    return np.minimum(0.02 + 0.003 * z * z, 0.15)


def _fit_band(Q: np.ndarray, u: np.ndarray, h0: float, iters: int = 3) -> tuple[np.ndarray, float, np.ndarray]:
    """Weighted least-squares plane (normal near ``u``) through the points of ``Q`` near height ``h0``.

    Returns the refined normal (sign of ``u``), the plane height ``u . p`` and the inlier mask.
    """
    tol = _plane_tol(Q[:, 2])
    wq = 1.0 / (tol * tol)
    sel = np.abs(Q @ u - h0) < tol
    for _ in range(iters):
        if sel.sum() < 10:
            break
        X = Q[sel]
        wt = wq[sel]
        c = (X * wt[:, None]).sum(0) / wt.sum()
        D = X - c
        C = (D * wt[:, None]).T @ D
        _, vecs = np.linalg.eigh(C)
        nrm = vecs[:, 0]
        if nrm @ u < 0:
            nrm = -nrm
        if nrm @ u < np.cos(np.radians(15)):
            break
        u = nrm
        h0 = float(c @ u)
        sel = np.abs(Q @ u - h0) < tol
    return u, h0, sel


def _extent(Q: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    """Robust in-plane extents (5-95 percentile spans, m) of points ``Q`` on a plane with normal ``u``."""
    if len(Q) < 5:
        return 0.0, 0.0
    R = upright_rotation(u)
    ab = Q @ R[:, :2]
    lo, hi = np.percentile(ab, [5, 95], axis=0)
    ea, eb = float(hi[0] - lo[0]), float(hi[1] - lo[1])
    return max(ea, eb), min(ea, eb)


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
    N = grid.normals[sub][nmask]
    if N.shape[0] * f < 30:
        return fallback
    P = grid.pmean[sub][nmask]
    n_valid = int(np.count_nonzero(grid.valid))
    Ns = N
    Pc = grid.points[sub][grid.valid[sub]]
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
    # floor: the lowest well-supported plane below the camera with (almost) nothing under
    # it; support counts all points on it (floors are often speckled, with few normals)
    hc = Pc @ u1
    floor = None
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
        floor = (h0, nin, e1, e2)
        break
    ceiling = None
    for h0, _cnt in reversed(peaks_dn):
        if h0 < 0.3:
            break
        on = np.abs(hc - h0) < tol_c
        if on.sum() < min_floor:
            continue
        e1, e2 = _extent(Pc[on][:: max(1, int(on.sum()) // 1500)], u1)
        if e2 >= 0.5 and int(np.count_nonzero(hc > h0 + 0.1 + 2 * tol_c)) <= max_below:
            ceiling = h0
            break
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


_JOINT_MIN_FRAC = 0.05


def _curvature(Q: np.ndarray, NQ: np.ndarray, u: np.ndarray) -> float:
    """Curvature (1/m) of the surface through points ``Q`` with normals ``NQ`` around the
    axis ``u``: slope of the normals' tangential tilt against the in-plane position
    (0 for a plane, 1/r for a sphere of radius r)."""
    if len(Q) < 5:
        return 0.0
    R = upright_rotation(u)[:, :2]
    a = Q @ R
    a = a - a.mean(axis=0)
    t = NQ @ R
    den = float((a * a).sum())
    return float((a * t).sum()) / den if den > 1e-9 else 0.0


def _joint_or_mode(groups: list[np.ndarray], u1: np.ndarray, n_valid: int, max_dev_deg: float) -> np.ndarray:
    """Joint plane-fit normal of ``groups`` when they are large enough to beat the normal
    mode ``u1`` (small planes seen at grazing angles bias least squares), else ``u1``."""
    if not groups or sum(len(g) for g in groups) < _JOINT_MIN_FRAC * n_valid:
        return u1
    uj = _fit_planes_joint(groups)
    if uj @ u1 < 0:
        uj = -uj
    return normalize(uj) if uj @ u1 > np.cos(np.radians(max_dev_deg)) else u1


def _plane_support(Q: np.ndarray, d: np.ndarray, bin_m: float = 0.03) -> int:
    """Largest number of points of ``Q`` on one plane with normal ``d`` (3-bin offset histogram)."""
    if len(Q) == 0:
        return 0
    o = Q @ d
    idx = ((o - o.min()) / bin_m).astype(np.int64)
    cnt = np.bincount(idx).astype(np.int64)
    sm = cnt.copy()
    sm[1:] += cnt[:-1]
    sm[:-1] += cnt[1:]
    return int(sm.max())


def _azimuth_mode(V: np.ndarray, R: np.ndarray, nb: int = 90) -> tuple[np.ndarray, int]:
    q = V @ R
    az = np.mod(np.arctan2(q[:, 1], q[:, 0]), np.pi)
    hist = np.bincount(np.minimum((az / np.pi * nb).astype(np.int64), nb - 1), minlength=nb).astype(np.float64)
    hs = hist + np.roll(hist, 1) + np.roll(hist, -1)
    k = int(np.argmax(hs))
    a = (k + 0.5) * np.pi / nb
    return R @ np.array([np.cos(a), np.sin(a), 0.0]), int(hs[k])


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
