"""Surface segmentation for the geometric proposer: neighbour links of the depth grid cut
at depth jumps, concave creases and colour edges; connected components of what is left."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..gravity import DepthGrid
from ..gravity_grid import work_array

if TYPE_CHECKING:
    from .geometric import GeometricConfig, ProposalDebug

#: one grid link direction: (jump, curvature, known, slice_a, slice_b), see ``Segmenter._link_features``
LinkFeatures = tuple[np.ndarray, np.ndarray, np.ndarray, tuple[slice, slice], tuple[slice, slice]]


def _pad0(a: np.ndarray, pad: int) -> np.ndarray:
    """``np.pad(a, pad)`` (zeros around a 2D array) without its per-call overhead."""
    out = np.zeros((a.shape[0] + 2 * pad, a.shape[1] + 2 * pad), a.dtype)
    out[pad : pad + a.shape[0], pad : pad + a.shape[1]] = a
    return out


class Segmenter:
    """Mixin of :class:`~.geometric.GeometricProposer`: link features, colour links,
    segments and the convex share of a mask's boundary (uses ``self.config``)."""

    config: GeometricConfig
    debug: ProposalDebug

    def _link_features(self, grid: DepthGrid, P: np.ndarray, valid: np.ndarray) -> list[LinkFeatures]:
        """Per grid link (axis 1: to the right neighbour, axis 0: to the one below):
        ``(jump, curvature, known, slice_a, slice_b)``. ``jump``: a depth discontinuity (step
        nearly along the viewing ray, or large); ``curvature``:
        ``(n_a - n_b) . (p_a - p_b) / |p_a - p_b|`` of the patches 2 nodes beyond each end
        (> 0 convex, < 0 concave; the link's own normals where those are unknown);
        ``known``: curvature available. Component-wise arrays (faster than (h, w, 3) dots)."""
        cfg = self.config
        h, w = valid.shape
        nv = grid.rvalid & valid
        cos_g = np.float32(np.cos(np.radians(cfg.graze_deg)))
        pad = 3
        Pc = [np.ascontiguousarray(P[..., i]) for i in range(3)]
        Nc = [np.ascontiguousarray(grid.rnormals[..., i]) for i in range(3)]
        Ppad = [_pad0(a, pad) for a in Pc]
        Npad = [_pad0(a, pad) for a in Nc]
        nvp = _pad0(nv, pad)
        rn = np.sqrt(Pc[0] * Pc[0] + Pc[1] * Pc[1] + Pc[2] * Pc[2]) + np.float32(1e-6)
        jthr = cfg.jump_abs + cfg.jump_rel * Pc[2]
        out = []
        for axis in (1, 0):
            if axis == 1:
                sa, sb = (slice(None), slice(0, w - 1)), (slice(None), slice(1, w))
                oa = (slice(pad, pad + h), slice(pad - 2, pad - 2 + w - 1))
                ob = (slice(pad, pad + h), slice(pad + 3, pad + 3 + w - 1))
            else:
                sa, sb = (slice(0, h - 1), slice(None)), (slice(1, h), slice(None))
                oa = (slice(pad - 2, pad - 2 + h - 1), slice(pad, pad + w))
                ob = (slice(pad + 3, pad + 3 + h - 1), slice(pad, pad + w))
            d = [c[sb] - c[sa] for c in Pc]
            dist = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + np.float32(1e-6)
            along = np.abs(d[0] * Pc[0][sa] + d[1] * Pc[1][sa] + d[2] * Pc[2][sa]) / (dist * rn[sa])
            za = Pc[2][sa]
            jt = jthr[sa]
            jump = (dist > jt) & ((along > cos_g) | (dist > 0.3 + 0.05 * za))
            dq = [c[ob] - c[oa] for c in Ppad]
            dqn = np.sqrt(dq[0] * dq[0] + dq[1] * dq[1] + dq[2] * dq[2]) + np.float32(1e-6)
            known = nvp[oa] & nvp[ob]
            curv = -((Npad[0][oa] - Npad[0][ob]) * dq[0] + (Npad[1][oa] - Npad[1][ob]) * dq[1]
                     + (Npad[2][oa] - Npad[2][ob]) * dq[2]) / dqn
            # no normals beyond the ends: the link's own normals, else strict continuity
            inner = ~known & nv[sa] & nv[sb]
            if inner.any():
                curv_i = -((Nc[0][sa] - Nc[0][sb]) * d[0] + (Nc[1][sa] - Nc[1][sb]) * d[1]
                           + (Nc[2][sa] - Nc[2][sb]) * d[2]) / dist
                curv = np.where(known, curv, np.where(inner, curv_i, np.float32(0)))
                known = known | inner
            else:
                curv = np.where(known, curv, np.float32(0))
            jump |= ~known & (dist > 0.5 * jt)
            out.append((jump, curv, known, sa, sb))
        return out

    def _color_links(self, rgb: np.ndarray, grid: DepthGrid) -> list[np.ndarray]:
        """Lab colour distance (8-bit units) of each grid link (axis 1, then axis 0)."""
        h, w = grid.shape
        s = grid.stride
        img = np.ascontiguousarray(rgb[: h * s, : w * s, :3])
        if img.dtype != np.uint8:
            img = np.clip(img, 0, 255).astype(np.uint8)
        if s > 1 and s & (s - 1) == 0:  # power of two: repeated exact halvings (bilinear at
            small = img  # scale 1/2 averages 2x2 blocks), 4x faster than INTER_AREA on uint8
            level = 0
            while small.shape[0] > h:
                hw = (small.shape[0] // 2, small.shape[1] // 2)
                # into reused buffers: a fresh half-resolution image per frame is page-faulted in
                buf = work_array(f"rgb_half{level}", (*hw, small.shape[2]), np.uint8)
                small = cv2.resize(small, (hw[1], hw[0]), dst=buf, interpolation=cv2.INTER_LINEAR)
                level += 1
        else:
            small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if s > 1 else img
        lab = cv2.cvtColor(small, cv2.COLOR_RGB2Lab)
        ch = [c.astype(np.float32) for c in cv2.split(lab)]
        dh = [c[:, 1:] - c[:, :-1] for c in ch]
        dv = [c[1:, :] - c[:-1, :] for c in ch]
        return [np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) for d in (dh, dv)]

    def _segments(self, obj: np.ndarray, feats, concave_deg: float, cut: list[np.ndarray] | None = None) -> np.ndarray:
        """Labels (h,w) int32 of depth-continuous, locally convex patches (0 = none);
        ``cut``: extra per-link cuts (axis 1, axis 0), e.g. colour edges."""
        h, w = obj.shape
        conc = np.float32(-2.0 * np.sin(np.radians(concave_deg) / 2))
        links = []
        for i, (jump, curv, known, sa, sb) in enumerate(feats):
            lk = obj[sa] & obj[sb] & ~jump & ~(known & (curv < conc))
            links.append(lk if cut is None else lk & ~cut[i])
        lh, lv = links
        self.debug.links = (lh, lv)
        img = np.zeros((2 * h - 1, 2 * w - 1), np.uint8)
        img[::2, ::2] = obj
        img[::2, 1::2] = lh
        img[1::2, ::2] = lv
        _, lab = cv2.connectedComponents(img, connectivity=4, ltype=cv2.CV_32S)
        return lab[::2, ::2]

    def _convex_boundary(self, mask: np.ndarray, valid: np.ndarray, feats) -> float:
        """Share of the links leaving ``mask`` (to valid points) that are convex, continuous edges."""
        conv = np.float32(2.0 * np.sin(np.radians(self.config.convex_deg) / 2))
        n_all = n_conv = 0
        for jump, curv, known, sa, sb in feats:
            leave = (mask[sa] & ~mask[sb] & valid[sb]) | (~mask[sa] & mask[sb] & valid[sa])
            n_all += int(np.count_nonzero(leave))
            n_conv += int(np.count_nonzero(leave & ~jump & known & (curv > conv)))
        return n_conv / max(n_all, 1)

    # ------------------------------------------------------------------------------
