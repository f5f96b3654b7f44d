"""Surface segmentation for the geometric proposer: neighbour links of the depth grid cut
at depth jumps, concave creases and colour edges; connected components of what is left."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..gravity import DepthGrid
from ..grid_kernels import link_features
from ..gravity_grid import work_array

if TYPE_CHECKING:
    from .geometric import GeometricConfig, ProposalDebug

#: one grid link direction: (jump, curvature, known, slice_a, slice_b), see ``Segmenter._link_features``
LinkFeatures = tuple[np.ndarray, np.ndarray, np.ndarray, tuple[slice, slice], tuple[slice, slice]]


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
        ``known``: curvature available. One compiled pass (:func:`~shape_detector.grid_kernels.link_features`)."""
        cfg = self.config
        h, w = valid.shape
        nv = grid.rvalid & valid
        cos_g = float(np.cos(np.radians(cfg.graze_deg)))
        jh, ch, kh, jv, cv, kv = link_features(P, grid.rnormals, nv, float(cfg.jump_abs), float(cfg.jump_rel), cos_g)
        return [(jh, ch, kh, (slice(None), slice(0, w - 1)), (slice(None), slice(1, w))),
                (jv, cv, kv, (slice(0, h - 1), slice(None)), (slice(1, h), slice(None)))]

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
