"""The strided depth grid shared by the gravity estimate and the geometric proposer:
block-mean camera-frame points and per-block normals (compiled passes in
:mod:`.grid_kernels`).

Frames: camera optical frame (x right, y down, z forward), metres."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from .grid_kernels import block_points, smoothed_normals

_REF_POINTS = 160 * 120  # point-count thresholds are for a VGA frame at stride 4
_NORMAL_K = 2  # central-difference half-baseline of the normals, in cells
_SCRATCH = threading.local()  # per-thread reusable work arrays (colour links)


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
    if depth.dtype != np.float32:
        depth = depth.astype(np.float32)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    pts, pm, bvalid, Z = block_points(depth, s, float(max_depth), fx, fy, cx, cy)
    u = (np.arange(w, dtype=np.float32) * s + 0.5 * (s - 1)).astype(np.float32)
    v = (np.arange(h, dtype=np.float32) * s + 0.5 * (s - 1)).astype(np.float32)
    if h >= 2 * _NORMAL_K + 1 and w >= 2 * _NORMAL_K + 1:
        normals, nvalid, rnormals, rvalid = smoothed_normals(pm, Z, _NORMAL_K)
    else:
        normals, rnormals = np.zeros((h, w, 3), np.float32), np.zeros((h, w, 3), np.float32)
        nvalid, rvalid = np.zeros((h, w), bool), np.zeros((h, w), bool)
    return DepthGrid(s, pts, bvalid, pm, normals, nvalid, u, v, (H, W), rnormals, rvalid)
