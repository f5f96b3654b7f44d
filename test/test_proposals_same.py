"""Fast paths of the geometric proposer and the depth grid against their plain numpy
definitions: radix sorts, sort-based unique, the compiled grid and link passes, greedy
de-duplication, and grids that later calls leave untouched (reused work buffers)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from shape_detector.gravity import make_grid
from shape_detector.gravity_planes import _percentiles_5_95
from shape_detector.grid_kernels import link_features
from shape_detector.proposals.evaluate import VGA_K
from shape_detector.synth.generate import generate_frame
from shape_detector.proposals.geo_hypotheses import _sorted_unique, _stable_order
from shape_detector.proposals.geo_ranking import _dedup, _iou_matrix


@pytest.mark.parametrize("hi", [1, 300, 65536, 70000])
def test_stable_order_is_stable_argsort(hi: int) -> None:
    rng = np.random.default_rng(hi)
    for lo in (0, -5):
        lab = rng.integers(lo, hi, 5000)
        assert np.array_equal(_stable_order(lab), np.argsort(lab, kind="stable"))
    assert _stable_order(np.zeros(0, np.int64)).size == 0


@pytest.mark.parametrize("hi", [50, 1 << 20, (1 << 32) - 1, 1 << 40])
def test_sorted_unique_is_unique_with_counts(hi: int) -> None:
    rng = np.random.default_rng(7)
    for lo in (0, -hi):
        a = rng.integers(lo, hi, 4000)
        a[:10] = hi - 1  # the largest key present
        u, c = _sorted_unique(a)
        ru, rc = np.unique(a, return_counts=True)
        assert np.array_equal(u, ru) and np.array_equal(c, rc)
    u, c = _sorted_unique(np.zeros(0, np.int64))
    assert u.size == 0 and c.size == 0


def _grid_reference(depth: np.ndarray, K: np.ndarray, s: int, max_depth: float) -> dict[str, np.ndarray]:
    """The depth grid by its plain numpy definition (see ``DepthGrid``)."""
    h, w = depth.shape[0] // s, depth.shape[1] // s
    d = depth[: h * s, : w * s].astype(np.float64).reshape(h, s, w, s).transpose(0, 2, 1, 3).reshape(h, w, s * s)
    ok = np.isfinite(d) & (d > 0) & (d <= max_depth)
    cnt = ok.sum(-1)
    valid = cnt > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(ok, d, 0).sum(-1) / cnt
    dmin = np.where(ok, d, np.inf).min(-1)
    dmax = np.where(ok, d, -np.inf).max(-1)
    smooth = valid & ~(dmax - dmin > 0.03 + 0.04 * dmin)
    u = np.arange(w) * s + 0.5 * (s - 1)
    v = np.arange(h) * s + 0.5 * (s - 1)
    ray = np.stack(np.broadcast_arrays(((u - K[0, 2]) / K[0, 0])[None, :], ((v - K[1, 2]) / K[1, 1])[:, None],
                                       np.ones((h, w))), -1)
    zc = np.where(valid, np.where(smooth, mean, dmin), np.nan)
    zm = np.where(smooth, mean, np.nan)
    pm = ray * zm[..., None]
    # central differences over +-2 cells, facing the camera, then the 3x3 mean (zero outside)
    k = 2
    raw = np.zeros((h, w, 3))
    good = np.zeros((h, w))
    for i in range(k, h - k):
        for j in range(k, w - k):
            if not (smooth[i, j] and smooth[i, j - k] and smooth[i, j + k] and smooth[i - k, j] and smooth[i + k, j]):
                continue
            a, b = pm[i, j + k] - pm[i, j - k], pm[i + k, j] - pm[i - k, j]
            lim = k * (0.6 * zm[i, j] + 0.2)
            n = np.cross(a, b)
            if abs(a[2]) < lim and abs(b[2]) < lim and np.linalg.norm(n) > 1e-12:
                n = n / np.linalg.norm(n)
                raw[i, j] = -n if n @ pm[i, j] > 0 else n
                good[i, j] = 1.0
    pad = np.pad(raw, ((1, 1), (1, 1), (0, 0)))
    gpad = np.pad(good, 1)
    mean_n = sum(pad[1 + di : 1 + di + h, 1 + dj : 1 + dj + w] for di in (-1, 0, 1) for dj in (-1, 0, 1)) / 9
    gcount = sum(gpad[1 + di : 1 + di + h, 1 + dj : 1 + dj + w] for di in (-1, 0, 1) for dj in (-1, 0, 1)) / 9
    ln = np.linalg.norm(mean_n, axis=-1)
    unit = mean_n / np.maximum(ln, 1e-12)[..., None]
    keep = (good > 0) & (ln > 0.85 * gcount) & (gcount > 0.5)
    keep[[0, -1], :] = False
    keep[:, [0, -1]] = False
    return dict(points=ray * zc[..., None], pmean=pm, valid=valid, normals=unit * keep[..., None], nvalid=keep,
                rnormals=unit, rvalid=gcount > 0.6)


def _noisy_depth(seed: int) -> np.ndarray:
    """A generated VGA depth frame with NaN holes, zeros, negatives, inf and far values."""
    rng = np.random.default_rng(seed)
    depth = generate_frame(20_000 + seed).depth.astype(np.float32)
    for bad in (np.nan, 0.0, -1.0, np.inf, 50.0):
        r, c = rng.integers(0, 440), rng.integers(0, 600)
        depth[r : r + rng.integers(1, 40), c : c + rng.integers(1, 40)] = bad
    return depth


@pytest.mark.parametrize("seed,s", [(0, 4), (1, 4), (2, 3), (3, 1)])
def test_grid_matches_its_numpy_definition(seed: int, s: int) -> None:
    depth = _noisy_depth(seed)
    if s == 1:
        depth = depth[::4, ::4].copy()  # a QQVGA frame at stride 1
    g = make_grid(depth, VGA_K if s != 1 else VGA_K * np.array([[0.25], [0.25], [1]]), stride=s, max_depth=8.0)
    ref = _grid_reference(depth, VGA_K if s != 1 else VGA_K * np.array([[0.25], [0.25], [1]]), s, 8.0)
    for name in ("valid", "nvalid", "rvalid"):
        # a mask may flip only where its threshold is met within float32 rounding
        assert np.mean(getattr(g, name) != ref[name]) < 1e-3, name
    both = g.nvalid & ref["nvalid"]
    for name in ("points", "pmean"):
        assert np.allclose(getattr(g, name), ref[name], atol=1e-4, equal_nan=True), name
    assert np.allclose(g.normals[both], ref["normals"][both], atol=1e-4)
    assert np.allclose(g.rnormals[g.rvalid & ref["rvalid"]], ref["rnormals"][g.rvalid & ref["rvalid"]], atol=1e-4)


def _links_reference(P: np.ndarray, N: np.ndarray, nv: np.ndarray, jump_abs: float, jump_rel: float,
                     cos_g: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Link features by their definition, one link at a time (see ``link_features``)."""
    h, w = nv.shape
    out = []
    for di, dj in ((0, 1), (1, 0)):
        shape = (h - di, w - dj)
        jump, curv, known = np.zeros(shape, bool), np.zeros(shape), np.zeros(shape, bool)
        for i in range(shape[0]):
            for j in range(shape[1]):
                a, b = (i, j), (i + di, j + dj)
                o, q = (i - 2 * di, j - 2 * dj), (i + 3 * di, j + 3 * dj)
                d = P[b] - P[a]
                dist = np.linalg.norm(d) + 1e-6
                along = abs(d @ P[a]) / (dist * (np.linalg.norm(P[a]) + 1e-6))
                jt = jump_abs + jump_rel * P[a][2]
                jump[i, j] = dist > jt and (along > cos_g or dist > 0.3 + 0.05 * P[a][2])
                if 0 <= min(o) and q[0] < h and q[1] < w and nv[o] and nv[q]:
                    e = P[q] - P[o]
                    curv[i, j] = -((N[o] - N[q]) @ e) / (np.linalg.norm(e) + 1e-6)
                    known[i, j] = True
                elif nv[a] and nv[b]:
                    curv[i, j] = -((N[a] - N[b]) @ d) / dist
                    known[i, j] = True
                jump[i, j] |= not known[i, j] and dist > 0.5 * jt
        out.append((jump, curv, known))
    return out


def test_link_features_match_their_definition() -> None:
    depth = _noisy_depth(4)[::2, ::2].copy()  # small enough for the per-link reference
    g = make_grid(depth, VGA_K * np.array([[0.5], [0.5], [1]]), stride=4, max_depth=8.0)
    P = np.where(g.valid[..., None], g.points, 0).astype(np.float32)
    nv = g.rvalid & g.valid
    cos_g = float(np.cos(np.radians(12.0)))
    got = link_features(P, g.rnormals, nv, 0.04, 0.03, cos_g)
    ref = _links_reference(P.astype(np.float64), g.rnormals.astype(np.float64), nv, 0.04, 0.03, cos_g)
    for axis, (jump, curv, known) in enumerate(ref):
        gj, gc, gk = got[3 * axis : 3 * axis + 3]
        assert np.array_equal(gk, known)
        assert np.mean(gj != jump) < 2e-3  # flips only at a threshold within float32 rounding
        assert np.allclose(gc, curv, atol=1e-4)
    assert known.any() and jump.any() and (curv < -0.1).any() and (curv > 0.1).any()


@pytest.mark.parametrize("n", [1, 2, 5, 20, 1999, 2000])
def test_percentiles_5_95_are_numpys(n: int) -> None:
    a = np.random.default_rng(n).normal(size=(n, 2))
    lo, hi = _percentiles_5_95(a)
    ref = np.percentile(a, [5, 95], axis=0)
    assert np.allclose(lo, ref[0], rtol=0, atol=1e-12) and np.allclose(hi, ref[1], rtol=0, atol=1e-12)


def _dedup_reference(boxes: np.ndarray, thr: float, limit: int) -> list[int]:
    iou = _iou_matrix(boxes)
    keep: list[int] = []
    for i in range(len(boxes)):
        if len(keep) >= limit:
            break
        if all(iou[i, k] <= thr for k in keep):
            keep.append(i)
    return keep


def test_dedup_matches_greedy_reference() -> None:
    rng = np.random.default_rng(3)
    for n in (0, 1, 5, 60):
        xy = rng.uniform(0, 100, (n, 2))
        wh = rng.uniform(5, 40, (n, 2))
        boxes = np.round(np.concatenate([xy, xy + wh], 1))
        for thr, limit in ((0.5, 100), (0.9, 30), (0.3, 4)):
            assert _dedup(boxes, thr, None, limit) == _dedup_reference(boxes, thr, limit)


def test_grids_survive_later_calls() -> None:
    """Work buffers are reused across calls; no returned array may share them."""
    rng = np.random.default_rng(0)
    fields = ["points", "valid", "pmean", "normals", "nvalid", "u", "v", "rnormals", "rvalid"]
    depth = (1.0 + rng.random((480, 640)) * 3.0).astype(np.float32)
    depth[100:140, 200:260] = np.nan
    g1 = make_grid(depth, VGA_K, stride=4)
    snap = copy.deepcopy(g1)
    make_grid(depth[::-1].copy() * 1.5, VGA_K, stride=4)
    for f in fields:
        assert np.array_equal(getattr(g1, f), getattr(snap, f), equal_nan=True), f


def _axial_mean_reference(n: np.ndarray, u: np.ndarray, angles=(10.0, 6.0, 4.0)) -> tuple[np.ndarray, int]:
    cnt, sub = 0, n
    for i, ang in enumerate(angles):
        c = sub @ u
        sel = np.abs(c) > np.cos(np.radians(ang))
        cnt = int(sel.sum())
        if cnt < 3:
            break
        sub, c = sub[sel], c[sel]
        s = (sub * np.sign(c)[:, None]).sum(0)
        u = s / max(np.linalg.norm(s), 1e-12)
        if i == 0:
            sub = n[np.abs(n @ u) > np.cos(np.radians(ang + 3.0))]
    return u, cnt


def _fit_band_reference(Q: np.ndarray, u: np.ndarray, h0: float, iters: int = 3):
    tol = np.minimum(0.02 + 0.003 * Q[:, 2] ** 2, 0.15)
    sel = np.abs(Q @ u - h0) < tol
    for _ in range(iters):
        if sel.sum() < 10:
            break
        X, wt = Q[sel], 1.0 / tol[sel] ** 2
        c = (X * wt[:, None]).sum(0) / wt.sum()
        nrm = np.linalg.eigh(((X - c) * wt[:, None]).T @ (X - c))[1][:, 0]
        nrm = -nrm if nrm @ u < 0 else nrm
        if nrm @ u < np.cos(np.radians(15)):
            break
        u, h0 = nrm, float(c @ nrm)
        sel = np.abs(Q @ u - h0) < tol
    return u, h0, sel


def test_gravity_kernels_match_their_numpy_definitions() -> None:
    from shape_detector.gravity_planes import _axial_mean, _fit_band

    rng = np.random.default_rng(5)
    up = np.array([0.05, -0.99, 0.12]) / np.linalg.norm([0.05, -0.99, 0.12])
    # normals: a floor family around up (both signs), a wall family, noise
    n = np.concatenate([up + 0.03 * rng.normal(size=(900, 3)), -up + 0.03 * rng.normal(size=(300, 3)),
                        np.cross(up, [1.0, 0, 0]) + 0.05 * rng.normal(size=(500, 3)), rng.normal(size=(400, 3))])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    for start in (up, up + [0.1, 0, 0], np.array([1.0, 0, 0])):
        start = start / np.linalg.norm(start)
        got, ref = _axial_mean(n, start), _axial_mean_reference(n, start)
        assert got[1] == ref[1] and np.allclose(got[0], ref[0], atol=1e-12)
    assert _axial_mean(n[:2], up)[1] < 3  # too few: the axis stays
    # points: a tilted floor plane 1.3 m below the camera with depth noise, plus clutter
    xz = rng.uniform([-2, 0.5], [2, 6], size=(3000, 2))
    P = np.stack([xz[:, 0], np.zeros(3000), xz[:, 1]], 1)
    P[:, 1] = -(up[0] * P[:, 0] + up[2] * P[:, 2] + 1.3) / up[1] + rng.normal(0, 0.01, 3000)
    P = np.concatenate([P, rng.uniform([-2, -1, 0.5], [2, 1, 6], size=(800, 3))])
    for u0, h in ((np.array([0.0, -1.0, 0.0]), -1.6), (up, -1.3), (np.array([0.0, -1.0, 0.0]), 5.0)):
        gu, gh, gs = _fit_band(P, u0, h)
        ru, rh, rs = _fit_band_reference(P, u0, h)
        assert np.allclose(gu, ru, atol=1e-9) and gh == pytest.approx(rh, abs=1e-9) and np.array_equal(gs, rs)
    fitted = _fit_band(P, np.array([0.0, -1.0, 0.0]), -1.6)
    assert np.allclose(fitted[0], up, atol=2e-3) and fitted[1] == pytest.approx(-1.3, abs=0.01)
