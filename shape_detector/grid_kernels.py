"""Compiled (numba, ``nogil``) passes of :func:`~shape_detector.gravity_grid.make_grid`.

Each is one pass over its input instead of a dozen full-array numpy temporaries, and
releases the GIL so the learned proposer's thread runs beside it. Frames: camera optical
frame (x right, y down, z forward), metres.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, error_model="numpy")
def block_points(depth: np.ndarray, s: int, max_depth: float, fx: float, fy: float, cx: float, cy: float):
    """Per ``s`` x ``s`` block of ``depth`` (float32 m; NaN, inf, <= 0 and > ``max_depth``
    invalid): ``points`` (h,w,3) float32 (the block mean on smooth blocks, the nearest
    sample on blocks spanning a depth edge, NaN without a valid sample), ``pmean`` (h,w,3)
    (block mean, NaN unless smooth), ``valid`` (h,w) bool and ``Z`` (h,w) float32 (the
    block mean where smooth, else 0)."""
    H, W = depth.shape
    h, w = H // s, W // s
    pts = np.empty((h, w, 3), np.float32)
    pm = np.empty((h, w, 3), np.float32)
    valid = np.zeros((h, w), np.bool_)
    Z = np.zeros((h, w), np.float32)
    tot = np.empty(w, np.float32)
    cnt = np.empty(w, np.float32)
    dmin = np.empty(w, np.float32)
    dmax = np.empty(w, np.float32)
    ok = np.empty(w * s, np.float32)  # one image row: 1 where valid
    val = np.empty(w * s, np.float32)  # the depth where valid, else 0
    low = np.empty(w * s, np.float32)  # the depth where valid, else 1e4
    nan = np.float32(np.nan)
    md = np.float32(max_depth)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    big = np.float32(1e4)
    for bi in range(h):
        tot[:] = 0.0
        cnt[:] = 0.0
        dmin[:] = big
        dmax[:] = 0.0
        for r in range(bi * s, bi * s + s):
            # a branch-free pass over the row (vectorised), then the block sums
            row = depth[r]
            for c in range(w * s):
                d = row[c]
                good = (d > zero) & (d <= md)  # False for NaN; inf > max_depth
                ok[c] = one if good else zero
                val[c] = d if good else zero
                low[c] = d if good else big
            for bj in range(w):
                t = tot[bj]
                n = cnt[bj]
                lo = dmin[bj]
                hi = dmax[bj]
                for c in range(bj * s, bj * s + s):
                    t += val[c]
                    n += ok[c]
                    lo = min(lo, low[c])
                    hi = max(hi, val[c])
                tot[bj] = t
                cnt[bj] = n
                dmin[bj] = lo
                dmax[bj] = hi
        rv = (np.float32(bi * s + 0.5 * (s - 1)) - np.float32(cy)) / np.float32(fy)
        for bj in range(w):
            ru = (np.float32(bj * s + 0.5 * (s - 1)) - np.float32(cx)) / np.float32(fx)
            if cnt[bj] == 0:
                for k in range(3):
                    pts[bi, bj, k] = nan
                    pm[bi, bj, k] = nan
                continue
            valid[bi, bj] = True
            mean = tot[bj] / cnt[bj]
            lo = dmin[bj]
            smooth = not (dmax[bj] - lo > np.float32(0.03) + np.float32(0.04) * lo)
            zc = mean if smooth else lo
            pts[bi, bj, 0] = ru * zc
            pts[bi, bj, 1] = rv * zc
            pts[bi, bj, 2] = zc
            if smooth:
                pm[bi, bj, 0] = ru * mean
                pm[bi, bj, 1] = rv * mean
                pm[bi, bj, 2] = mean
                Z[bi, bj] = mean
            else:
                for k in range(3):
                    pm[bi, bj, k] = nan
    return pts, pm, valid, Z


@numba.njit(cache=True, nogil=True, error_model="numpy")
def smoothed_normals(pm: np.ndarray, Z: np.ndarray, k: int):
    """Normals of the smooth blocks (``Z`` > 0, points ``pm``) from central differences over
    +-``k`` cells, facing the camera, then the 3x3 mean of those unit normals (zeros
    outside the grid). Returns ``normals`` (h,w,3) (the mean, normalised, where the
    neighbourhood agrees; 0 elsewhere), ``nvalid``, ``rnormals`` (the normalised mean
    everywhere) and ``rvalid`` (most of the 3x3 neighbourhood has raw normals)."""
    h, w = Z.shape
    raw = np.zeros((h, w, 4), np.float32)  # unit normal, then 1 where it exists
    for i in range(k, h - k):
        for j in range(k, w - k):
            z = Z[i, j]
            if not (z > 0 and Z[i, j - k] > 0 and Z[i, j + k] > 0 and Z[i - k, j] > 0 and Z[i + k, j] > 0):
                continue
            ax = pm[i, j + k, 0] - pm[i, j - k, 0]
            ay = pm[i, j + k, 1] - pm[i, j - k, 1]
            az = pm[i, j + k, 2] - pm[i, j - k, 2]
            bx = pm[i + k, j, 0] - pm[i - k, j, 0]
            by = pm[i + k, j, 1] - pm[i - k, j, 1]
            bz = pm[i + k, j, 2] - pm[i - k, j, 2]
            lim = k * (np.float32(0.6) * z + np.float32(0.2))
            if not (abs(az) < lim and abs(bz) < lim):
                continue
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            nrm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if not nrm > 1e-12:
                continue
            facing = nx * pm[i, j, 0] + ny * pm[i, j, 1] + nz * z
            inv = np.float32(1.0) / nrm
            if facing > 0:
                inv = -inv
            raw[i, j, 0] = nx * inv
            raw[i, j, 1] = ny * inv
            raw[i, j, 2] = nz * inv
            raw[i, j, 3] = 1.0
    # 3x3 mean (zero outside the grid) as a row pass and a column pass
    rs = np.zeros((h, w, 4), np.float32)
    for i in range(h):
        for j in range(w):
            for q in range(4):
                v = raw[i, j, q]
                if j > 0:
                    v += raw[i, j - 1, q]
                if j < w - 1:
                    v += raw[i, j + 1, q]
                rs[i, j, q] = v
    normals = np.zeros((h, w, 3), np.float32)
    rnormals = np.zeros((h, w, 3), np.float32)
    nvalid = np.zeros((h, w), np.bool_)
    rvalid = np.zeros((h, w), np.bool_)
    ninth = np.float32(1.0 / 9.0)
    for i in range(h):
        for j in range(w):
            sx = rs[i, j, 0]
            sy = rs[i, j, 1]
            sz = rs[i, j, 2]
            g = rs[i, j, 3]
            if i > 0:
                sx += rs[i - 1, j, 0]
                sy += rs[i - 1, j, 1]
                sz += rs[i - 1, j, 2]
                g += rs[i - 1, j, 3]
            if i < h - 1:
                sx += rs[i + 1, j, 0]
                sy += rs[i + 1, j, 1]
                sz += rs[i + 1, j, 2]
                g += rs[i + 1, j, 3]
            sx *= ninth
            sy *= ninth
            sz *= ninth
            g *= ninth
            ln = np.sqrt(sx * sx + sy * sy + sz * sz)
            inv = np.float32(1.0) / max(ln, np.float32(1e-12))
            rnormals[i, j, 0] = sx * inv
            rnormals[i, j, 1] = sy * inv
            rnormals[i, j, 2] = sz * inv
            rvalid[i, j] = g > 0.6
            if raw[i, j, 3] > 0 and ln > 0.85 * g and g > 0.5 and 0 < i < h - 1 and 0 < j < w - 1:
                nvalid[i, j] = True
                normals[i, j, 0] = sx * inv
                normals[i, j, 1] = sy * inv
                normals[i, j, 2] = sz * inv
    return normals, nvalid, rnormals, rvalid


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _links_row(ax, ay, az, bx, by, bz, nax, nay, naz, nbx, nby, nbz, va, vb,
               ox, oy, oz, qx, qy, qz, nox, noy, noz, nqx, nqy, nqz, vo, vq,
               jump_abs, jump_rel, cos_g, jump_out, curv_out, known_out, n):
    """Jump, curvature and known flag (see :func:`link_features`) of ``n`` links a -> b of one
    row, ``o`` / ``q`` the cells two beyond ``a`` and ``b``: component rows in, branch-free
    (vectorised)."""
    eps = np.float32(1e-6)
    zero = np.float32(0.0)
    ja = np.float32(jump_abs)
    jr = np.float32(jump_rel)
    for j in range(n):
        dx = bx[j] - ax[j]
        dy = by[j] - ay[j]
        dz = bz[j] - az[j]
        dist = np.sqrt(dx * dx + dy * dy + dz * dz) + eps
        rn = np.sqrt(ax[j] * ax[j] + ay[j] * ay[j] + az[j] * az[j]) + eps
        along = abs(dx * ax[j] + dy * ay[j] + dz * az[j]) / (dist * rn)
        jt = ja + jr * az[j]
        jump = (dist > jt) & ((along > cos_g) | (dist > np.float32(0.3) + np.float32(0.05) * az[j]))
        ex = qx[j] - ox[j]
        ey = qy[j] - oy[j]
        ez = qz[j] - oz[j]
        qn = np.sqrt(ex * ex + ey * ey + ez * ez) + eps
        c_far = -((nox[j] - nqx[j]) * ex + (noy[j] - nqy[j]) * ey + (noz[j] - nqz[j]) * ez) / qn
        c_own = -((nax[j] - nbx[j]) * dx + (nay[j] - nby[j]) * dy + (naz[j] - nbz[j]) * dz) / dist
        k_far = vo[j] & vq[j]
        k_own = va[j] & vb[j]
        known = k_far | k_own
        curv_out[j] = c_far if k_far else (c_own if k_own else zero)
        known_out[j] = known
        jump_out[j] = jump | (~known & (dist > np.float32(0.5) * jt))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def link_features(P: np.ndarray, N: np.ndarray, nv: np.ndarray, jump_abs: float, jump_rel: float, cos_g: float):
    """Features of the grid's neighbour links, to the right neighbour ``(h, w-1)`` and to
    the one below ``(h-1, w)``: ``jump`` (a depth step nearly along the viewing ray, or a
    large one), ``curv`` (``(n_a - n_b) . (p_a - p_b) / |p_a - p_b|`` of the patches two
    cells beyond each end, > 0 convex; the link's own normals where those are unknown; 0
    when neither is known), ``known``. ``P`` (h,w,3) float32 points (0 where invalid), ``N``
    (h,w,3) unit normals, ``nv`` (h,w) their mask."""
    h, w = nv.shape
    cg = np.float32(cos_g)
    # zero-padded by 3 cells with no normals: a link whose far cells leave the grid is
    # "not known there", like any other, and one row kernel serves every link
    pad = 3
    hp, wp = h + 2 * pad, w + 2 * pad
    px, py, pz = np.zeros((hp, wp), np.float32), np.zeros((hp, wp), np.float32), np.zeros((hp, wp), np.float32)
    nx, ny, nz = np.zeros((hp, wp), np.float32), np.zeros((hp, wp), np.float32), np.zeros((hp, wp), np.float32)
    vp = np.zeros((hp, wp), np.bool_)
    for i in range(h):
        for j in range(w):
            px[i + pad, j + pad], py[i + pad, j + pad], pz[i + pad, j + pad] = P[i, j, 0], P[i, j, 1], P[i, j, 2]
            nx[i + pad, j + pad], ny[i + pad, j + pad], nz[i + pad, j + pad] = N[i, j, 0], N[i, j, 1], N[i, j, 2]
            vp[i + pad, j + pad] = nv[i, j]
    wl, hl = max(w - 1, 0), max(h - 1, 0)
    jh, ch, kh = np.zeros((h, wl), np.bool_), np.zeros((h, wl), np.float32), np.zeros((h, wl), np.bool_)
    jv, cv, kv = np.zeros((hl, w), np.bool_), np.zeros((hl, w), np.float32), np.zeros((hl, w), np.bool_)
    c0, c1 = pad, pad + w
    for i in range(h):  # to the right neighbour: a = j, b = j + 1, o = j - 2, q = j + 3
        r = i + pad
        a, b, o, q = slice(c0, c1), slice(c0 + 1, c1 + 1), slice(c0 - 2, c1 - 2), slice(c0 + 3, c1 + 3)
        _links_row(px[r, a], py[r, a], pz[r, a], px[r, b], py[r, b], pz[r, b],
                   nx[r, a], ny[r, a], nz[r, a], nx[r, b], ny[r, b], nz[r, b], vp[r, a], vp[r, b],
                   px[r, o], py[r, o], pz[r, o], px[r, q], py[r, q], pz[r, q],
                   nx[r, o], ny[r, o], nz[r, o], nx[r, q], ny[r, q], nz[r, q], vp[r, o], vp[r, q],
                   jump_abs, jump_rel, cg, jh[i], ch[i], kh[i], wl)
    for i in range(hl):  # to the one below: rows a = i, b = i + 1, o = i - 2, q = i + 3
        ra, rb, ro, rq = i + pad, i + pad + 1, i + pad - 2, i + pad + 3
        c = slice(c0, c1)
        _links_row(px[ra, c], py[ra, c], pz[ra, c], px[rb, c], py[rb, c], pz[rb, c],
                   nx[ra, c], ny[ra, c], nz[ra, c], nx[rb, c], ny[rb, c], nz[rb, c], vp[ra, c], vp[rb, c],
                   px[ro, c], py[ro, c], pz[ro, c], px[rq, c], py[rq, c], pz[rq, c],
                   nx[ro, c], ny[ro, c], nz[ro, c], nx[rq, c], ny[rq, c], nz[rq, c], vp[ro, c], vp[rq, c],
                   jump_abs, jump_rel, cg, jv[i], cv[i], kv[i], w)
    return jh, ch, kh, jv, cv, kv
