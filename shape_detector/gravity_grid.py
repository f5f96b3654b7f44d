"""The strided depth grid shared by the gravity estimate and the geometric proposer:
block-mean camera-frame points and per-block normals, pure numpy + cv2.

Frames: camera optical frame (x right, y down, z forward), metres."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

_REF_POINTS = 160 * 120  # point-count thresholds are for a VGA frame at stride 4
_NORMAL_K = (2, 0)  # central-difference half-baselines in cells: near, far (beyond 2.5 m; 0: off)
_SCRATCH = threading.local()  # per-thread reusable work arrays (make_grid, colour links)


def work_array(name: str, shape: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
    """A reusable per-thread work array ``name`` (contents undefined). Full-resolution
    temporaries allocated afresh each frame are returned to the OS and page-faulted back
    in on the next one, which costs more than the cheap passes that fill them."""
    bufs: dict[str, np.ndarray] = _SCRATCH.__dict__.setdefault("bufs", {})
    a = bufs.get(name)
    if a is None or a.shape != shape or a.dtype != dtype:
        a = bufs[name] = np.empty(shape, dtype)
    return a


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
        """(rows, columns) of the grid."""
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
    # work copy (float32) in a reused buffer; nothing returned refers to it
    dc = work_array("depth", (h * s, w * s))
    np.copyto(dc, depth[: h * s, : w * s], casting="unsafe")
    cv2.patchNaNs(dc, 0.0)
    cv2.threshold(dc, float(max_depth), 0.0, cv2.THRESH_TOZERO_INV, dst=dc)
    cv2.threshold(dc, 0.0, 0.0, cv2.THRESH_TOZERO, dst=dc)  # negatives / inf -> 0
    okf = cv2.threshold(dc, 0.0, 1.0, cv2.THRESH_BINARY, dst=work_array("valid", dc.shape))[1]
    if s > 1:
        area = cv2.INTER_AREA
        frac = cv2.resize(okf, (w, h), interpolation=area)
        msum = cv2.resize(dc, (w, h), interpolation=area)
        alt = cv2.addWeighted(dc, 1.0, okf, -1e4, 1e4, dst=work_array("alt", dc.shape))  # invalid -> 1e4
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
        n1, g1 = _raw_normals(X, Y, Z, msm, _NORMAL_K[0], out=work_array("n1", (h, w, 3)))
        if _NORMAL_K[1] and h >= 7 and w >= 7:
            # far away the depth noise swamps short baselines: 3-block differences there
            n3_, g3 = _raw_normals(X, Y, Z, msm, _NORMAL_K[1])
            far = g3 & (Z > 2.5)
            nraw = np.where(far[..., None], n3_, n1)
            good = far | (g1 & ~(Z > 2.5)) | (g1 & ~g3)
        else:
            nraw, good = n1, g1
        # smooth (3x3 mean of unit normals); keep normals whose neighbourhood agrees
        # (h, w, 3) temporaries in reused buffers, see work_array
        nb = cv2.blur(nraw, (3, 3), dst=work_array("nb", (h, w, 3)), borderType=cv2.BORDER_CONSTANT)
        gcount = cv2.blur(good.astype(np.float32), (3, 3), borderType=cv2.BORDER_CONSTANT)
        ln = np.sqrt(cv2.transform(cv2.multiply(nb, nb, dst=work_array("nb2", (h, w, 3))), np.ones((1, 3), np.float32)))
        keep = good & (ln > 0.85 * gcount) & (gcount > 0.5)
        keep[0, :] = keep[-1, :] = False
        keep[:, 0] = keep[:, -1] = False
        unit = np.divide(nb, np.maximum(ln, 1e-12)[..., None], out=work_array("unit", (h, w, 3)))
        np.multiply(unit, keep[..., None], out=normals)
        nvalid[:] = keep
        rnormals[:] = unit
        rvalid[:] = gcount > 0.6
    return DepthGrid(s, pts, bvalid, pm, normals, nvalid, u, v, (H, W), rnormals, rvalid)


def _block_reduce(a: np.ndarray, s: int, op) -> np.ndarray:
    """``op`` (np.minimum / np.maximum) over each ``s`` x ``s`` block of ``a`` (shape divisible)."""
    if s == 1:
        return a
    # accumulate in place: one row-reduced and one block-reduced array, not 2 (s - 1)
    r = op(a[0::s], a[1::s])
    for i in range(2, s):
        op(r, a[i::s], out=r)
    c = op(r[:, 0::s], r[:, 1::s])
    for j in range(2, s):
        op(c, r[:, j::s], out=c)
    return c


def _raw_normals(X: np.ndarray, Y: np.ndarray, Z: np.ndarray, m: np.ndarray, k: int,
                 out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (h,w,3) facing the camera from central differences over +-``k`` cells
    (0 at the border, at invalid cells and across depth discontinuities) and their mask.
    ``X, Y, Z``: block-mean points with 0 where ``m`` (valid) is False; ``out``: optional
    (h,w,3) float32 array to write the normals to (overwritten entirely)."""
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
    if out is None:
        out = np.zeros((h, w, 3), np.float32)
    else:
        out.fill(0.0)
    good = np.zeros((h, w), bool)
    oc = out[c]  # components written in place (no stacked temporary)
    np.multiply(nx, scale, out=oc[..., 0])
    np.multiply(ny, scale, out=oc[..., 1])
    np.multiply(nz, scale, out=oc[..., 2])
    good[c] = gi
    return out, good


# ---------------------------------------------------------------------------------------
