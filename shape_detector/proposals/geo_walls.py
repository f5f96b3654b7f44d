"""Room walls for the geometric proposer: vertical planes found by a Hough vote of
vertical-normal points, refined by line fits and tested (see :mod:`.geometric`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from .geometric import GeometricConfig, ProposalDebug

_REF_POINTS = 160 * 120  # point-count thresholds are for a VGA frame at stride 4


class WallFinder:
    """Mixin of :class:`~.geometric.GeometricProposer`: ``_walls`` (uses ``self.config``,
    ``self.debug`` and ``self._convex_boundary``)."""

    config: GeometricConfig
    debug: ProposalDebug
    _convex_boundary: Callable[..., float]  # from Segmenter

    def _walls(self, grid, obj, X, Y, hgt, z, R, feats) -> list[tuple[np.ndarray, float]]:
        """Vertical planes that bound the room: [(horizontal normal (2,) in U, offset m)].

        Candidates are the peaks of a (normal azimuth, offset) Hough vote of vertical-normal
        points, refined by 2D line fits of their footprint band and tested together
        (matrix form): wide, tall (or leaving the image at the top), (almost) nothing
        behind, and no convex edges along their boundary (those are furniture faces)."""
        cfg = self.config
        h, w = obj.shape
        min_pts = cfg.wall_min_points * (h * w) / _REF_POINTS
        # the vote uses every 2nd row / column (4x fewer normals, counts x 4)
        sub2 = (slice(None, None, 2), slice(None, None, 2))
        Nu = grid.normals[sub2] @ R.astype(np.float32)
        vert = obj[sub2] & grid.nvalid[sub2] & (np.abs(Nu[..., 2]) < 0.26)  # within 15 deg of vertical
        if 4 * vert.sum() < min_pts:
            return []
        nx, ny = Nu[..., 0][vert], Nu[..., 1][vert]
        nn = np.sqrt(nx * nx + ny * ny)
        nx, ny = nx / nn, ny / nn
        xv, yv = X[sub2][vert], Y[sub2][vert]
        rho = xv * nx + yv * ny  # negative: normals face the camera
        peaks = _hough_peaks(nx, ny, rho, cfg.max_depth, cfg.wall_candidates, min_pts)
        if not peaks:
            return []
        lines = _initial_lines(peaks, nx, ny, rho)
        if lines is None:
            return []
        nvec, r0 = lines
        # candidate statistics on a subsample of the object points
        obj_idx = np.flatnonzero(obj)
        sub = max(1, len(obj_idx) // 1500)
        obj_idx = obj_idx[::sub]
        xo, yo, ho, zo = X.ravel()[obj_idx], Y.ravel()[obj_idx], hgt.ravel()[obj_idx], z.ravel()[obj_idx]
        vo = obj_idx // w
        wtol = (cfg.wall_tol + 0.003 * zo * zo)[None, :]
        nvec, r0 = _refine_lines(nvec, r0, xo, yo, wtol)
        off = nvec[:, :1] * xo[None, :] + nvec[:, 1:] * yo[None, :] - r0[:, None]
        band = np.abs(off) < wtol
        nb = band.sum(1)
        along = -nvec[:, 1:] * xo[None, :] + nvec[:, :1] * yo[None, :]
        lo_h, hi_h = _masked_quantiles(np.broadcast_to(ho, band.shape), band, 0.03, 0.97, 0.05, -0.5, 4.0)
        lo_a, hi_a = _masked_quantiles(along, band, 0.03, 0.97, 0.1, -cfg.max_depth - 2, cfg.max_depth + 2)
        top_rows = (band & (vo <= 1)[None, :]).sum(1) * sub
        tall = (hi_h >= 2.0) | (top_rows >= 3)
        ext_h = hi_h - lo_h
        good = (nb * sub >= min_pts) & (hi_a - lo_a >= cfg.wall_min_width)
        good &= (ext_h >= cfg.wall_min_height) | ((ext_h >= 0.4) & tall)
        # (almost) nothing behind a wall: anywhere, or -- rising to the ceiling -- within its
        # own lateral extent (recesses, pillars, doors beside it)
        bh = off < -(0.15 + wtol)
        behind_all = bh.sum(1)
        behind_loc = (bh & (along > lo_a[:, None]) & (along < hi_a[:, None])).sum(1)
        good &= (behind_all <= 0.05 * nb + 10) | ((hi_h >= 2.0) & (behind_loc <= cfg.wall_behind_frac * nb + 10))
        walls: list[tuple[np.ndarray, float]] = []
        good_idx = np.flatnonzero(good)
        # the on-wall tolerance (m) per grid point: the same for every candidate
        gtol = cfg.wall_tol + 0.003 * z * z if len(good_idx) else None
        for k in good_idx:
            nk, rk = nvec[k].astype(np.float64), float(r0[k])
            if any(abs(rk - r1) < 0.1 and nk @ n1 > 0.995 for n1, r1 in walls):
                continue
            # furniture faces end in convex edges (to their top / side faces), walls in
            # concave corners, occlusions or the image border
            on = obj & (np.abs(X * nk[0] + Y * nk[1] - rk) < gtol)
            convex = self._convex_boundary(on, obj, feats)
            self.debug.wall_candidates.append(
                dict(n=nk, rho=rk, nb=int(nb[k]) * sub, h=(lo_h[k], hi_h[k]), a=hi_a[k] - lo_a[k], convex=convex,
                     behind=int(behind_all[k]) * sub)
            )
            if convex > cfg.wall_max_convex:
                continue
            walls.append((nk, rk))
            if len(walls) >= 4:
                break
        return walls


def _hough_peaks(nx: np.ndarray, ny: np.ndarray, rho: np.ndarray, max_depth: float, max_peaks: int,
                 min_pts: float) -> list[tuple[float, float]]:
    """Peaks ``(normal azimuth (rad), offset (m))`` of a (4 deg, 5 cm) Hough vote of points with
    unit horizontal normals ``(nx, ny)`` at offsets ``rho`` (upright frame U), best first: at most
    ``max_peaks``, each with at least ``min_pts / 2`` votes (counted x 4: the voters are every 2nd
    row and column), each suppressing its neighbourhood."""
    nab, rb = 90, 0.05
    ia = (np.mod(np.arctan2(ny, nx), 2 * np.pi) / (2 * np.pi) * nab).astype(np.int64) % nab
    rmin = -max_depth - 1.0
    nrb = int((max_depth + 2.0) / rb)
    ir = np.clip(((rho - rmin) / rb).astype(np.int64), 0, nrb - 1)
    hist = np.bincount(ia * nrb + ir, minlength=nab * nrb).reshape(nab, nrb).astype(np.float32)
    hs = cv2.blur(hist, (3, 3), borderType=cv2.BORDER_CONSTANT) * 9
    peaks = []
    for _ in range(max_peaks):
        k = int(np.argmax(hs))
        ka, kr = divmod(k, nrb)
        if 4 * hs[ka, kr] < min_pts * 0.5:
            break
        for a in range(ka - 2, ka + 3):
            hs[a % nab, max(kr - 4, 0) : kr + 5] = 0
        peaks.append(((ka + 0.5) * 2 * np.pi / nab, rmin + (kr + 0.5) * rb))
    return peaks


def _initial_lines(peaks: list[tuple[float, float]], nx: np.ndarray, ny: np.ndarray,
                   rho: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Initial wall lines ``(normals (K, 2), offsets (K,) m)`` in the upright frame U: the mean
    normal and offset of each Hough peak's members (within 10 cm and 10 deg); peaks with under
    5 members are dropped, None when none is left."""
    ang = np.array([p[0] for p in peaks])
    r0 = np.array([p[1] for p in peaks])
    mem = (np.abs(rho[None, :] - r0[:, None]) < 0.1) & (
        nx[None, :] * np.cos(ang)[:, None] + ny[None, :] * np.sin(ang)[:, None] > np.cos(np.radians(10))
    )
    cnt = mem.sum(1)
    ok = cnt >= 5
    if not ok.any():
        return None
    memf = mem[ok].astype(np.float32)
    nvec = np.stack([memf @ nx, memf @ ny], 1)
    nvec /= np.linalg.norm(nvec, axis=1, keepdims=True)
    r0 = (memf @ rho) / cnt[ok]
    return nvec, r0


def _refine_lines(nvec: np.ndarray, r0: np.ndarray, xo: np.ndarray, yo: np.ndarray,
                  wtol: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wall lines ``(normals (K, 2), offsets (K,) m)`` in the upright frame U refined twice by a
    2D line fit of the points ``(xo, yo)`` within ``wtol`` (m) of each; a line keeps its previous
    fit when its band has under 10 points or the fit turns it by 15 deg or more."""
    mom = np.stack([np.ones_like(xo), xo, yo, xo * xo, xo * yo, yo * yo], 1).astype(np.float64)
    for _it in range(2):  # refine: 2D line fit of each band's footprint
        off = nvec[:, :1] * xo[None, :] + nvec[:, 1:] * yo[None, :] - r0[:, None]
        band = (np.abs(off) < wtol).astype(np.float64)
        M = band @ mom  # (K, 6): n, sx, sy, sxx, sxy, syy
        n_ = np.maximum(M[:, 0], 1.0)
        mx, my = M[:, 1] / n_, M[:, 2] / n_
        cxx = M[:, 3] / n_ - mx * mx
        cxy = M[:, 4] / n_ - mx * my
        cyy = M[:, 5] / n_ - my * my
        ang_l = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # line direction
        nn2 = np.stack([-np.sin(ang_l), np.cos(ang_l)], 1)
        nn2 *= np.where((nn2 * nvec).sum(1) < 0, -1.0, 1.0)[:, None]
        upd = (M[:, 0] >= 10) & ((nn2 * nvec).sum(1) > np.cos(np.radians(15)))
        nvec = np.where(upd[:, None], nn2, nvec)
        r0 = np.where(upd, mx * nvec[:, 0] + my * nvec[:, 1], r0)
    return nvec, r0


def _masked_quantiles(
    V: np.ndarray, M: np.ndarray, qlo: float, qhi: float, bin_w: float, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Approximate ``qlo`` / ``qhi`` quantiles (histogram, ``bin_w`` bins over [lo, hi]) of
    each row of ``V`` (K, n) restricted to the row's mask ``M`` (K, n)."""
    K = V.shape[0]
    nb = int(np.ceil((hi - lo) / bin_w))
    idx = np.clip(((V - lo) / bin_w).astype(np.int64), 0, nb - 1)
    rows = np.broadcast_to(np.arange(K)[:, None], idx.shape)
    hist = np.bincount((rows * nb + idx)[M], minlength=K * nb).reshape(K, nb)
    cum = np.cumsum(hist, axis=1)
    tot = np.maximum(cum[:, -1:], 1)
    i_lo = np.argmax(cum >= qlo * tot, axis=1)
    i_hi = np.argmax(cum >= qhi * tot, axis=1)
    return lo + i_lo * bin_w, lo + (i_hi + 1) * bin_w
