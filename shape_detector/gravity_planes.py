"""Plane and direction fits of the gravity estimate (:mod:`.gravity`): joint plane fits,
normal modes, height peaks, plane bands, extents and curvature; pure numpy + cv2.

Frames: camera optical frame or the upright frame of a candidate ``u``, metres."""

from __future__ import annotations

import cv2
import numpy as np

from .geometry import normalize, upright_rotation
from .gravity_kernels import axial_mean, fit_band

_JOINT_MIN_FRAC = 0.05


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
    """Refine the axis ``u`` as the mean of the (sign-aligned) ``n`` in shrinking cones; the
    later cones look only at the first cone's members (+ 3 degrees). Returns (axis, count
    in the last cone); see :func:`.gravity_kernels.axial_mean`."""
    cones = np.cos(np.radians(np.asarray(angles_deg, dtype=np.float64)))
    margin = float(np.cos(np.radians(float(angles_deg[0]) + 3.0)))
    axis, cnt = axial_mean(np.ascontiguousarray(n, dtype=np.float64), np.asarray(u, dtype=np.float64), cones, margin)
    return axis, int(cnt)


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
    peaks: list[tuple[float, int]] = []
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

    Returns the refined normal (sign of ``u``), the plane height ``u . p`` and the inlier mask
    (see :func:`.gravity_kernels.fit_band`: a refit turning the normal by 15 degrees or more
    stops it).
    """
    Q = np.ascontiguousarray(Q, dtype=np.float64)
    un, hh, sel = fit_band(Q, _plane_tol(Q[:, 2]), np.asarray(u, dtype=np.float64), float(h0), int(iters),
                           float(np.cos(np.radians(15))))
    return un, float(hh), sel


def _extent(Q: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    """Robust in-plane extents (5-95 percentile spans, m) of points ``Q`` on a plane with normal ``u``."""
    if len(Q) < 5:
        return 0.0, 0.0
    R = upright_rotation(u)
    ab = Q @ R[:, :2]
    lo, hi = _percentiles_5_95(ab)
    ea, eb = float(hi[0] - lo[0]), float(hi[1] - lo[1])
    return max(ea, eb), min(ea, eb)


def _percentiles_5_95(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.percentile(a, [5, 95], axis=0)`` (linear interpolation) of ``a`` (n, k), n >= 1,
    by one partial sort: several times faster for the few thousand rows of a plane."""
    n = len(a)
    out = []
    pos = (0.05 * (n - 1), 0.95 * (n - 1))
    lows = [int(p) for p in pos]
    part = np.partition(a, sorted({k for lo in lows for k in (lo, min(lo + 1, n - 1))}), axis=0)
    for p, lo in zip(pos, lows):
        below, above = part[lo], part[min(lo + 1, n - 1)]
        out.append(below + (above - below) * (p - lo))
    return out[0], out[1]


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
