"""Negative evidence: is a track's space seen empty in this frame?

A track's parts (its fused primitives, else its box) are sampled on a small lattice of
world points. Each sample is projected into the frame's depth image (camera optical frame:
x right, y down, z forward; metres) and classified like the detector's free-space carving
(:mod:`shape_detector.postprocess.free_space`):

* **seen through** -- the measured depth lies behind the sample by more than
  ``margin + margin_per_m * z``: the camera sees past that point, so it is empty;
* **surface** -- the measured depth is within that margin: something is there;
* **hidden** -- the measured depth is nearer: the point is behind something (the object's
  own front, or another object), nothing is known about it;
* **out of view** -- outside the image, behind the camera, beyond ``max_range`` or without a
  valid depth.

The track is *in view* when at least ``min_in_view`` of its samples are in the image with a
valid depth; it is *seen empty* when, in addition, at least ``min_free`` samples and a share
``free_share`` of the in-view ones are seen through. A present object hides its own
inside and shows its surface, so only a removed object (or a box the image clearly
contradicts) is seen empty; an occluded or out-of-view one never is.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..geometry import measured_depth



@dataclass(frozen=True)
class EmptyParams:
    """Settings of :func:`seen_empty` (metres unless said)."""

    #: seen-through test: measured depth > sample depth + margin + margin_per_m * depth
    margin: float = 0.08
    margin_per_m: float = 0.02
    #: samples beyond this range are out of view (depth too noisy there)
    max_range: float = 5.0
    #: share of the samples that must be in the image with a valid depth
    min_in_view: float = 0.5
    #: share of the in-view samples that must be seen through ...
    free_share: float = 0.85
    #: ... and at least this many of them
    min_free: int = 6
    #: lattice points per part axis (n**3 samples per part)
    lattice: int = 3


@functools.lru_cache(maxsize=8)
def unit_lattice(n: int) -> np.ndarray:
    """(n**3, 3) centres of an ``n`` x ``n`` x ``n`` split of the unit cube centred at 0 (read-only)."""
    t = (np.arange(n) + 0.5) / n - 0.5
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    g.flags.writeable = False
    return g


def part_samples(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], n: int = 3) -> np.ndarray:
    """World points (P * n**3, 3) on an ``n``-lattice inside each (center, size, rotation) part
    (at the centres of an ``n`` x ``n`` x ``n`` split of the part)."""
    g = unit_lattice(n)
    out = [np.asarray(c, float) + (g * np.asarray(s, float)) @ np.asarray(R, float).T for c, s, R in parts]
    return np.concatenate(out) if out else np.zeros((0, 3))


def classify_samples(world: np.ndarray, T_world_camera: np.ndarray, depth: np.ndarray, K: np.ndarray,
                     p: EmptyParams) -> tuple[int, int, int]:
    """(in view, seen through, surface) counts of the world points ``world`` (N,3)."""
    T = np.asarray(T_world_camera, dtype=np.float64)
    cam = (np.asarray(world, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]
    z = cam[:, 2]
    front = (z > 0.1) & (z < p.max_range)
    if not front.any():
        return 0, 0, 0
    cam, z = cam[front], z[front]
    d = measured_depth(cam, depth, K)
    known = np.isfinite(d)
    tol = p.margin + p.margin_per_m * z
    free = known & (d > z + tol)
    surface = known & (np.abs(d - z) <= tol)
    return int(known.sum()), int(free.sum()), int(surface.sum())


def seen_empty(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], T_world_camera: np.ndarray,
               depth: np.ndarray, K: np.ndarray, params: EmptyParams | None = None) -> bool | None:
    """True when the parts' space is seen empty in this frame, False when in view and not
    empty, None when not in view (see the module docstring)."""
    p = params or EmptyParams()
    pts = part_samples(parts, p.lattice)
    if len(pts) == 0:
        return None
    n_view, n_free, _ = classify_samples(pts, T_world_camera, depth, K, p)
    if n_view < p.min_in_view * len(pts):
        return None
    return bool(n_free >= p.min_free and n_free >= p.free_share * n_view)
