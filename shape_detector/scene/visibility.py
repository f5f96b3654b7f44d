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
    if not parts:
        return np.zeros((0, 3))
    c, s, R = (np.asarray([part[i] for part in parts], dtype=np.float64) for i in range(3))
    # point j of part i: c_i + R_i (g_j * s_i)
    return (c[:, None, :] + np.einsum("pab,pjb->pja", R, unit_lattice(n)[None] * s[:, None, :])).reshape(-1, 3)


def sample_states(world: np.ndarray, T_world_camera: np.ndarray, depth: np.ndarray, K: np.ndarray,
                  p: EmptyParams) -> tuple[np.ndarray, np.ndarray]:
    """Per world point (N,3): (in view with a valid depth, seen through) as bool arrays (N,)."""
    T = np.asarray(T_world_camera, dtype=np.float64)
    cam = (np.asarray(world, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]
    z = cam[:, 2]
    front = (z > 0.1) & (z < p.max_range)
    known = np.zeros(len(z), bool)
    free = np.zeros(len(z), bool)
    if front.any():
        d = measured_depth(cam[front], depth, K)
        known[front] = np.isfinite(d)
        with np.errstate(invalid="ignore"):
            free[front] = d > z[front] + p.margin + p.margin_per_m * z[front]
    return known, free


def seen_empty_many(tracks_parts: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]],
                    T_world_camera: np.ndarray, depth: np.ndarray, K: np.ndarray,
                    params: EmptyParams | None = None) -> list[bool | None]:
    """:func:`seen_empty` of several objects' parts at once (one projection for all)."""
    p = params or EmptyParams()
    per = len(unit_lattice(p.lattice))
    counts = np.array([len(parts) * per for parts in tracks_parts], np.int64)
    if counts.sum() == 0:
        return [None] * len(tracks_parts)
    known, free = sample_states(part_samples([q for parts in tracks_parts for q in parts], p.lattice),
                                T_world_camera, depth, K, p)
    owner = np.repeat(np.arange(len(counts)), counts)
    n_view = np.bincount(owner, known, len(counts))
    n_free = np.bincount(owner, free, len(counts))
    out: list[bool | None] = []
    for n, v, f in zip(counts, n_view, n_free):
        out.append(None if n == 0 or v < p.min_in_view * n else bool(f >= p.min_free and f >= p.free_share * v))
    return out


def seen_empty(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], T_world_camera: np.ndarray,
               depth: np.ndarray, K: np.ndarray, params: EmptyParams | None = None) -> bool | None:
    """True when the parts' space is seen empty in this frame, False when in view and not
    empty, None when not in view (see the module docstring)."""
    return seen_empty_many([parts], T_world_camera, depth, K, params)[0]
