"""Compiled (numba, ``nogil``) loops of the gravity fit (:mod:`.gravity_planes`): the
axial mean of normals in shrinking cones and the weighted plane fit of a height band.

Each replaces a handful of numpy passes (with a temporary each) over a few thousand points,
several times a frame. Frames: the camera optical frame, metres."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, error_model="numpy")
def axial_mean(n: np.ndarray, u: np.ndarray, cos_cones: np.ndarray, cos_first_margin: float):
    """``(axis, count)``: ``u`` (3,) refined as the normalised sum of the sign-aligned unit
    vectors ``n`` (N,3) float64 within each cone (``|n . u| > cos_cones[i]``) in turn; the
    first cone's result is re-gathered from all of ``n`` within ``cos_first_margin`` and the
    later cones look only at those. Stops (keeping the previous axis) when a cone holds
    under 3; ``count``: the last cone's members."""
    N = n.shape[0]
    idx = np.arange(N)
    m = N
    cnt = 0
    ux, uy, uz = u[0], u[1], u[2]
    for i in range(cos_cones.shape[0]):
        ca = cos_cones[i]
        sx = 0.0
        sy = 0.0
        sz = 0.0
        k = 0
        for t in range(m):
            j = idx[t]
            c = n[j, 0] * ux + n[j, 1] * uy + n[j, 2] * uz
            if abs(c) > ca:
                sg = 1.0 if c > 0 else -1.0
                sx += sg * n[j, 0]
                sy += sg * n[j, 1]
                sz += sg * n[j, 2]
                idx[k] = j
                k += 1
        cnt = k
        if cnt < 3:
            break
        norm = max(np.sqrt(sx * sx + sy * sy + sz * sz), 1e-12)
        ux, uy, uz = sx / norm, sy / norm, sz / norm
        m = k
        if i == 0:
            m = 0
            for j in range(N):
                if abs(n[j, 0] * ux + n[j, 1] * uy + n[j, 2] * uz) > cos_first_margin:
                    idx[m] = j
                    m += 1
    out = np.empty(3)
    out[0], out[1], out[2] = ux, uy, uz
    return out, cnt


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _band(Q: np.ndarray, tol: np.ndarray, u: np.ndarray, h0: float) -> np.ndarray:
    """Points of ``Q`` within ``tol`` of the plane ``u . p = h0``."""
    sel = np.empty(Q.shape[0], np.bool_)
    for j in range(Q.shape[0]):
        sel[j] = abs(Q[j, 0] * u[0] + Q[j, 1] * u[1] + Q[j, 2] * u[2] - h0) < tol[j]
    return sel


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fit_band(Q: np.ndarray, tol: np.ndarray, u: np.ndarray, h0: float, iters: int, cos_max_turn: float):
    """``(normal, height, inliers)``: the plane with normal near ``u`` through the points of
    ``Q`` (N,3) float64 within their band half-widths ``tol`` (N,) m of ``u . p = h0``,
    refit ``iters`` times by least squares weighted by ``1 / tol^2``; a refit with under 10
    inliers, or one turning the normal by more than ``acos(cos_max_turn)``, stops it."""
    N = Q.shape[0]
    wq = 1.0 / (tol * tol)
    u = u.copy()
    sel = _band(Q, tol, u, h0)
    for _ in range(iters):
        if sel.sum() < 10:
            break
        W = 0.0
        c = np.zeros(3)
        for j in range(N):
            if sel[j]:
                W += wq[j]
                for a in range(3):
                    c[a] += wq[j] * Q[j, a]
        c /= W
        C = np.zeros((3, 3))
        for j in range(N):
            if sel[j]:
                for a in range(3):
                    da = Q[j, a] - c[a]
                    for b in range(3):
                        C[a, b] += wq[j] * da * (Q[j, b] - c[b])
        _, vecs = np.linalg.eigh(C)
        nrm = vecs[:, 0].copy()
        if nrm[0] * u[0] + nrm[1] * u[1] + nrm[2] * u[2] < 0:
            nrm = -nrm
        if nrm[0] * u[0] + nrm[1] * u[1] + nrm[2] * u[2] < cos_max_turn:
            break
        u = nrm
        h0 = c[0] * u[0] + c[1] * u[1] + c[2] * u[2]
        sel = _band(Q, tol, u, h0)
    return u, h0, sel
