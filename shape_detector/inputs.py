"""Validation and normalisation of detector inputs (pure numpy).

Every public entry point funnels its arrays through :func:`normalize_inputs`, so bad
input fails early with a ``ValueError`` that names the offending argument, and the rest
of the pipeline can assume clean types: rgb HxWx3 uint8, depth HxW float32 metres with NaN
for invalid, K 3x3 float64 with positive focal lengths.
"""

from __future__ import annotations

import numpy as np


def depth_to_metres(depth: np.ndarray, depth_scale: float | None = None) -> np.ndarray:
    """HxW depth as float32 metres, NaN where invalid.

    ``uint16`` input is millimetres (REP 118, 0 = invalid) unless ``depth_scale`` (metres
    per unit) is given; float input is metres (NaN, Inf and <= 0 are invalid) and is scaled
    by ``depth_scale`` when given.
    """
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.ndim != 2:
        raise ValueError(f"depth must be HxW, got shape {d.shape}")
    if np.issubdtype(d.dtype, np.integer):
        scale = 0.001 if depth_scale is None else float(depth_scale)
        out = d.astype(np.float32) * np.float32(scale)
        out[d == 0] = np.nan
        return out
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"depth dtype {d.dtype} not supported (uint16 mm or float metres)")
    out = d.astype(np.float32, copy=True)
    if depth_scale is not None:
        out *= np.float32(depth_scale)
    out[~np.isfinite(out) | (out <= 0)] = np.nan
    return out


def check_intrinsics(K: np.ndarray) -> np.ndarray:
    """K as a 3x3 float64 array; raises ``ValueError`` for non-finite or non-positive focals."""
    K = np.asarray(K, dtype=np.float64)
    if K.size == 9:
        K = K.reshape(3, 3)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError("K contains NaN/Inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}")
    return K


def check_rgb(rgb: np.ndarray) -> np.ndarray:
    """rgb as HxWx3 uint8 (greyscale HxW is replicated; RGBA drops alpha)."""
    a = np.asarray(rgb)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"rgb must be HxWx3, got shape {a.shape}")
    if a.shape[2] == 4:
        a = a[:, :, :3]
    if a.dtype != np.uint8:
        if np.issubdtype(a.dtype, np.floating) and np.nanmax(a, initial=0.0) <= 1.0:
            a = np.clip(np.nan_to_num(a) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        else:
            a = np.clip(a, 0, 255).astype(np.uint8)
    return a


def normalize_inputs(
    rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, depth_scale: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``(rgb uint8 HxWx3, depth float32 m HxW NaN-invalid, K 3x3)``.

    Raises ``ValueError`` naming both sizes when rgb and depth differ (the caller decides
    whether to resize; the detector does not guess registration).
    """
    rgb_n = check_rgb(rgb)
    depth_m = depth_to_metres(depth, depth_scale)
    if rgb_n.shape[:2] != depth_m.shape:
        raise ValueError(
            f"rgb size {rgb_n.shape[1]}x{rgb_n.shape[0]} differs from depth size "
            f"{depth_m.shape[1]}x{depth_m.shape[0]} (depth must be registered to the colour camera)"
        )
    return rgb_n, depth_m, check_intrinsics(K)
