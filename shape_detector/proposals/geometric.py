"""Class-agnostic 2D proposals from 3D geometry (+ colour when given), numpy + cv2 only.

Pipeline on one strided back-projection (:class:`~shape_detector.gravity.DepthGrid`,
``stride`` x ``stride`` pixel blocks) shared with the gravity estimate:

1. **gravity + floor** -- :func:`~shape_detector.gravity.estimate_up` (or the given ``up``):
   heights above the floor plane (above the lowest points when no floor is seen).
2. **structure removal** -- floor (height < a few cm, growing with depth noise),
   ceiling and anything above ``max_height``, and big vertical planes that are room
   walls: peaks of a Hough vote of (normal azimuth, offset) of vertical-normal points,
   refined by 2D line fits and accepted when wide, tall (or leaving the image at the
   top) and with (almost) nothing behind them; points behind a wall go too.
3. **segments** -- connected components of the image grid whose neighbour links are cut
   at depth jumps (steps nearly along the viewing ray), at concave creases (normals of
   the patches two cells beyond each end of the link) and, with an RGB frame, at colour
   edges (Lab distance of block means): roughly convex, depth-continuous, uniformly
   coloured surface patches.
4. **gravity-aware grouping** on a 2D footprint grid (``cell`` m cells on the floor
   plane): segment ``j`` is *inside* segment ``i`` when most of ``j``'s footprint cells are
   also ``i``'s. Hypotheses, several per object where the split is ambiguous:

   * ``core``: a segment plus the segments inside and *below* it (legs under a seat or a
     table top),
   * ``stack``: a segment plus everything inside its footprint (a chair seat with its
     back; a table with what stands on it),
   * ``group``: connected components of the "inside" relation (whole stacked objects),
   * ``blob``: connected components of the (closed) footprint occupancy (everything
     touching, e.g. a bed with its night stands),
   * ``layer`` / ``layer2``: blobs split where the footprint's top-height map steps
     (a night stand flush beside a dresser), and pairs of such layers meeting at a step
     (a chair's seat and back).

   Each hypothesis' grid blocks give its 2D box; tiny, flat or implausibly large ones
   are dropped, exact duplicates merged, the rest scored by kind x 3D-size plausibility
   x agreement between hypotheses, near-duplicates (IoU > ``dedup_iou``) suppressed and
   the best ``max_proposals`` kept. Recall is the aim: the network rejects the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry import upright_rotation
from ..gravity import DepthGrid, GravityConfig, GravityEstimate, auto_stride, estimate_floor_along, estimate_up, make_grid
from . import Proposal

_REF_POINTS = 160 * 120  # point-count thresholds are for a VGA frame at stride 4
#: stats rows: umin vmin umax vmax xmin ymin xmax ymax hmax hmin; sign turning all into minima
_SIGN = np.array([1, 1, -1, -1, 1, 1, -1, -1, -1, 1], np.float64)


@dataclass
class GeometricConfig:
    """Parameters of :class:`GeometricProposer` (metres, pixels, degrees)."""

    stride: int | None = None  # grid block size in pixels; None: ~160 x 120 blocks (VGA -> 4)
    max_depth: float = 8.0
    cell: float = 0.05  # footprint grid cell
    floor_margin: float = 0.04  # points lower than this above the floor are floor
    max_height: float = 2.3  # nothing we detect is taller
    wall_min_points: int = 100
    wall_min_height: float = 1.0  # vertical extent of a wall's visible part
    wall_min_width: float = 0.6
    wall_tol: float = 0.05
    wall_behind_frac: float = 0.25  # points behind a wall, relative to its own support
    wall_max_convex: float = 0.3  # share of a wall's boundary links that are convex edges
    wall_candidates: int = 6  # Hough peaks tested
    remove_behind_walls: bool = False  # also drop points seen beyond a wall (through openings)
    convex_deg: float = 15.0
    jump_abs: float = 0.04  # depth step that always cuts a link (plus jump_rel * z)
    jump_rel: float = 0.03
    graze_deg: float = 12.0  # links closer than this to the viewing ray are depth jumps
    #: one segmentation per entry: (crease angle in degrees that cuts links, colour distance
    #: (8-bit Lab) that cuts links or None); the hypotheses of all are pooled
    #: (without an RGB frame the colour cut is skipped)
    segmentations: tuple[tuple[float, float | None], ...] = ((20.0, 20.0),)
    layer_step: float = 0.12  # top-height step that splits footprint blobs (0: off)
    split_length: float = 1.3  # segments longer than this (m) are also cut into equal parts (0: off)
    split_max_segments: int = 4
    contain_frac: float = 0.5  # share of j's footprint in i's for "j inside i"
    below_margin: float = 0.10
    min_points: int = 6  # grid points of a seed segment
    min_height: float = 0.15  # top of a hypothesis above the floor
    max_extent: float = 4.0  # footprint extent of a hypothesis
    min_box_px: float = 10.0
    pad_px: float = 0.0
    pad_bottom_px: float = 6.0  # the floor band cut from object bottoms
    dedup_iou: float = 0.9
    consensus_iou: float = 0.8
    max_proposals: int = 30
    gravity: GravityConfig = field(default_factory=GravityConfig)


@dataclass
class ProposalDebug:
    """Intermediate results of the last call (for tests and figures)."""

    grid: DepthGrid | None = None
    object_mask: np.ndarray | None = None
    floor_mask: np.ndarray | None = None
    wall_mask: np.ndarray | None = None
    segments: np.ndarray | None = None
    links: tuple[np.ndarray, np.ndarray] | None = None
    walls: list[tuple[np.ndarray, float]] = field(default_factory=list)
    wall_candidates: list[dict] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    features: np.ndarray | None = None  # ranking features of the candidates (before NMS)
    candidates: np.ndarray | None = None  # their boxes


def _pad0(a: np.ndarray, pad: int) -> np.ndarray:
    """``np.pad(a, pad)`` (zeros around a 2D array) without its per-call overhead."""
    out = np.zeros((a.shape[0] + 2 * pad, a.shape[1] + 2 * pad), a.dtype)
    out[pad : pad + a.shape[0], pad : pad + a.shape[1]] = a
    return out


class GeometricProposer:
    """``proposer(depth, K, up=None, rgb=None) -> (GravityEstimate, [Proposal])``.

    ``depth``: HxW float32 metres (NaN / 0 invalid); ``K``: 3x3; ``up``: gravity-up in the
    camera frame if known (then it is used as is, source 'prior', confidence 1; the floor
    is still measured along it), else estimated from the depth; ``rgb``: HxWx3 uint8 RGB
    registered to ``depth`` (optional: adds colour edges to the segmentation). Proposals
    are class-agnostic (``class_name`` None), best first; ``self.debug`` keeps the last
    call's intermediate masks.
    """

    def __init__(self, config: GeometricConfig | None = None):
        self.config = config or GeometricConfig()
        self.debug = ProposalDebug()

    # ------------------------------------------------------------------------------
    def __call__(
        self, depth: np.ndarray, K: np.ndarray, up: np.ndarray | None = None, rgb: np.ndarray | None = None
    ) -> tuple[GravityEstimate, list[Proposal]]:
        cfg = self.config
        K = np.asarray(K, dtype=np.float64)
        grid = make_grid(depth, K, stride=self.stride_for(np.shape(depth)), max_depth=cfg.max_depth)
        if up is None:
            grav = estimate_up(None, K, grid=grid, config=cfg.gravity)
        else:
            grav = estimate_floor_along(grid, K, np.asarray(up, np.float64), cfg.gravity)
        props = self.propose(grid, grav, rgb)
        return grav, props

    def stride_for(self, shape: tuple[int, ...]) -> int:
        """The grid stride for an image of ``shape`` (the configured one, or automatic)."""
        return int(self.config.stride) if self.config.stride else auto_stride(shape)

    # ------------------------------------------------------------------------------
    def propose(self, grid: DepthGrid, grav: GravityEstimate, rgb: np.ndarray | None = None) -> list[Proposal]:
        cfg = self.config
        dbg = ProposalDebug(grid=grid)
        self.debug = dbg
        h, w = grid.shape
        P = grid.points
        valid = grid.valid
        R = upright_rotation(grav.up)
        Pf = np.where(valid[..., None], P, 0.0).astype(np.float32)
        Q = Pf @ R.astype(np.float32)  # upright: x right, y forward, z up
        X, Y, Zu = Q[..., 0], Q[..., 1], Q[..., 2]
        z = Pf[..., 2]
        if grav.floor_height is not None:
            hgt = Zu + np.float32(grav.floor_height)
        else:
            zs = Zu[valid]
            hgt = Zu - (np.float32(np.percentile(zs, 1)) if zs.size else np.float32(0))
        tol = np.minimum(0.02 + 0.003 * z * z, 0.15)
        floor = valid & (hgt < np.maximum(cfg.floor_margin, tol))
        obj = valid & ~floor & (hgt < cfg.max_height)
        if grav.ceiling_height is not None and grav.floor_height is not None:
            obj &= hgt < grav.ceiling_height - np.maximum(0.05, tol)
        feats = self._link_features(grid, Pf, valid & ~floor)
        walls = self._walls(grid, obj, X, Y, hgt, z, R, feats)
        dbg.walls = walls
        wall_mask = np.zeros_like(obj)
        if walls:
            Nu = grid.normals @ R.astype(np.float32)
            for nrm, rho in walls:
                off = X * nrm[0] + Y * nrm[1] - rho
                wtol = cfg.wall_tol + 0.003 * z * z
                ncos = Nu[..., 0] * nrm[0] + Nu[..., 1] * nrm[1]
                on = (np.abs(off) < wtol) & (~grid.nvalid | (ncos > 0.8))
                wall_mask |= valid & (on | ((off < -wtol) & cfg.remove_behind_walls))
            obj &= ~wall_mask
        dbg.floor_mask, dbg.wall_mask, dbg.object_mask = floor, wall_mask, obj
        if obj.sum() < cfg.min_points:
            return []
        color = None
        if rgb is not None and any(c is not None for _, c in cfg.segmentations):
            color = self._color_links(rgb, grid)
        pd = self._point_data(grid, obj, X, Y, hgt)
        cands = []
        levels = list(dict.fromkeys((lv, cthr if color is not None else None) for lv, cthr in cfg.segmentations))
        for lv, cthr in levels:
            seg = self._segments(obj, feats, float(lv), None if cthr is None else [c > cthr for c in color])
            if dbg.segments is None:
                dbg.segments = seg
            cands.append(self._hypotheses(grid, pd, seg))
        if cfg.layer_step > 0:
            cands.append(self._layers(grid, pd))
        boxes = np.concatenate([c[0] for c in cands])
        feats = np.concatenate([c[1] for c in cands])
        kinds = [k for c in cands for k in c[2]]
        if len(boxes) == 0:
            return []
        # identical boxes (one segment's core == stack, or equal across segmentations):
        # keep the best-ranked hypothesis' features, count the duplicates
        score0 = rank_features(np.concatenate([feats, np.zeros((len(feats), 1))], 1)) @ _RANK_W
        bi = np.clip(np.round(boxes), 0, 32767).astype(np.int64)
        key = ((bi[:, 0] * 32768 + bi[:, 1]) * 32768 + bi[:, 2]) * 32768 + bi[:, 3]
        o = np.lexsort((-score0, key))
        ks = key[o]
        first = o[np.r_[True, ks[1:] != ks[:-1]]]
        dup = np.diff(np.r_[np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]]), len(ks)])
        boxes, feats = boxes[first], feats[first]
        kinds = [kinds[i] for i in first]
        # consensus: boxes that several hypotheses / segmentations agree on rank higher
        iou = _iou_matrix(boxes)
        agree = (iou > cfg.consensus_iou).astype(np.int64) @ dup - 1
        dbg.features = np.concatenate([feats, np.minimum(agree, 8)[:, None] / 8.0], 1)
        dbg.candidates = boxes
        score = 1.0 / (1.0 + np.exp(-(rank_features(dbg.features) @ _RANK_W)))
        order = np.argsort(-score, kind="stable")
        boxes, score = boxes[order], score[order]
        kinds = [kinds[i] for i in order]
        keep = _dedup(boxes, cfg.dedup_iou, iou[np.ix_(order, order)], cfg.max_proposals)
        dbg.kinds = [kinds[i] for i in keep]
        return [Proposal(tuple(boxes[i]), None, float(score[i]), "geometric") for i in keep]

    # ------------------------------------------------------------------------------
    def _walls(self, grid, obj, X, Y, hgt, z, R, feats) -> list[tuple[np.ndarray, float]]:
        """Vertical planes that bound the room: [(horizontal normal (2,) in U, offset m)].

        Candidates are the peaks of a (normal azimuth, offset) Hough vote of vertical-normal
        points, refined by 2D line fits of their footprint band and tested together
        (matrix form): wide, tall (or leaving the image at the top), (almost) nothing
        behind, and no convex edges along their boundary (those are furniture faces)."""
        cfg = self.config
        h, w = obj.shape
        min_pts = cfg.wall_min_points * (h * w) / _REF_POINTS
        # the vote uses every 2nd row / column (4x fewer normals, counts x 4)
        sub2 = (slice(None, None, 2), slice(None, None, 2))
        Nu = grid.normals[sub2] @ R.astype(np.float32)
        vert = obj[sub2] & grid.nvalid[sub2] & (np.abs(Nu[..., 2]) < 0.26)  # within 15 deg of vertical
        if 4 * vert.sum() < min_pts:
            return []
        nx, ny = Nu[..., 0][vert], Nu[..., 1][vert]
        nn = np.sqrt(nx * nx + ny * ny)
        nx, ny = nx / nn, ny / nn
        xv, yv = X[sub2][vert], Y[sub2][vert]
        rho = xv * nx + yv * ny  # negative: normals face the camera
        nab, rb = 90, 0.05
        ia = (np.mod(np.arctan2(ny, nx), 2 * np.pi) / (2 * np.pi) * nab).astype(np.int64) % nab
        rmin = -cfg.max_depth - 1.0
        nrb = int((cfg.max_depth + 2.0) / rb)
        ir = np.clip(((rho - rmin) / rb).astype(np.int64), 0, nrb - 1)
        hist = np.bincount(ia * nrb + ir, minlength=nab * nrb).reshape(nab, nrb).astype(np.float32)
        hs = cv2.blur(hist, (3, 3), borderType=cv2.BORDER_CONSTANT) * 9
        peaks = []
        for _ in range(cfg.wall_candidates):
            k = int(np.argmax(hs))
            ka, kr = divmod(k, nrb)
            if 4 * hs[ka, kr] < min_pts * 0.5:
                break
            for a in range(ka - 2, ka + 3):
                hs[a % nab, max(kr - 4, 0) : kr + 5] = 0
            peaks.append(((ka + 0.5) * 2 * np.pi / nab, rmin + (kr + 0.5) * rb))
        if not peaks:
            return []
        ang = np.array([p[0] for p in peaks])
        r0 = np.array([p[1] for p in peaks])
        # initial normals / offsets: mean of each peak's member normals and offsets
        mem = (np.abs(rho[None, :] - r0[:, None]) < 0.1) & (
            nx[None, :] * np.cos(ang)[:, None] + ny[None, :] * np.sin(ang)[:, None] > np.cos(np.radians(10))
        )
        cnt = mem.sum(1)
        ok = cnt >= 5
        if not ok.any():
            return []
        memf = mem[ok].astype(np.float32)
        nvec = np.stack([memf @ nx, memf @ ny], 1)
        nvec /= np.linalg.norm(nvec, axis=1, keepdims=True)
        r0 = (memf @ rho) / cnt[ok]
        K = len(r0)
        # candidate statistics on a subsample of the object points
        obj_idx = np.flatnonzero(obj)
        sub = max(1, len(obj_idx) // 1500)
        obj_idx = obj_idx[::sub]
        xo, yo, ho, zo = X.ravel()[obj_idx], Y.ravel()[obj_idx], hgt.ravel()[obj_idx], z.ravel()[obj_idx]
        vo = obj_idx // w
        wtol = (cfg.wall_tol + 0.003 * zo * zo)[None, :]
        mom = np.stack([np.ones_like(xo), xo, yo, xo * xo, xo * yo, yo * yo], 1).astype(np.float64)
        for _it in range(2):  # refine: 2D line fit of each band's footprint
            off = nvec[:, :1] * xo[None, :] + nvec[:, 1:] * yo[None, :] - r0[:, None]
            band = (np.abs(off) < wtol).astype(np.float64)
            M = band @ mom  # (K, 6): n, sx, sy, sxx, sxy, syy
            n_ = np.maximum(M[:, 0], 1.0)
            mx, my = M[:, 1] / n_, M[:, 2] / n_
            cxx = M[:, 3] / n_ - mx * mx
            cxy = M[:, 4] / n_ - mx * my
            cyy = M[:, 5] / n_ - my * my
            ang_l = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # line direction
            nn2 = np.stack([-np.sin(ang_l), np.cos(ang_l)], 1)
            nn2 *= np.where((nn2 * nvec).sum(1) < 0, -1.0, 1.0)[:, None]
            upd = (M[:, 0] >= 10) & ((nn2 * nvec).sum(1) > np.cos(np.radians(15)))
            nvec = np.where(upd[:, None], nn2, nvec)
            r0 = np.where(upd, mx * nvec[:, 0] + my * nvec[:, 1], r0)
        off = nvec[:, :1] * xo[None, :] + nvec[:, 1:] * yo[None, :] - r0[:, None]
        band = np.abs(off) < wtol
        nb = band.sum(1)
        along = -nvec[:, 1:] * xo[None, :] + nvec[:, :1] * yo[None, :]
        lo_h, hi_h = _masked_quantiles(np.broadcast_to(ho, band.shape), band, 0.03, 0.97, 0.05, -0.5, 4.0)
        lo_a, hi_a = _masked_quantiles(along, band, 0.03, 0.97, 0.1, -cfg.max_depth - 2, cfg.max_depth + 2)
        top_rows = (band & (vo <= 1)[None, :]).sum(1) * sub
        tall = (hi_h >= 2.0) | (top_rows >= 3)
        ext_h = hi_h - lo_h
        good = (nb * sub >= min_pts) & (hi_a - lo_a >= cfg.wall_min_width)
        good &= (ext_h >= cfg.wall_min_height) | ((ext_h >= 0.4) & tall)
        # (almost) nothing behind a wall: anywhere, or -- rising to the ceiling -- within its
        # own lateral extent (recesses, pillars, doors beside it)
        bh = off < -(0.15 + wtol)
        behind_all = bh.sum(1)
        behind_loc = (bh & (along > lo_a[:, None]) & (along < hi_a[:, None])).sum(1)
        good &= (behind_all <= 0.05 * nb + 10) | ((hi_h >= 2.0) & (behind_loc <= cfg.wall_behind_frac * nb + 10))
        walls: list[tuple[np.ndarray, float]] = []
        for k in np.flatnonzero(good):
            nk, rk = nvec[k].astype(np.float64), float(r0[k])
            if any(abs(rk - r1) < 0.1 and nk @ n1 > 0.995 for n1, r1 in walls):
                continue
            # furniture faces end in convex edges (to their top / side faces), walls in
            # concave corners, occlusions or the image border
            on = obj & (np.abs(X * nk[0] + Y * nk[1] - rk) < cfg.wall_tol + 0.003 * z * z)
            convex = self._convex_boundary(on, obj, feats)
            self.debug.wall_candidates.append(
                dict(n=nk, rho=rk, nb=int(nb[k]) * sub, h=(lo_h[k], hi_h[k]), a=hi_a[k] - lo_a[k], convex=convex,
                     behind=int(behind_all[k]) * sub)
            )
            if convex > cfg.wall_max_convex:
                continue
            walls.append((nk, rk))
            if len(walls) >= 4:
                break
        return walls

    # ------------------------------------------------------------------------------
    def _link_features(self, grid: DepthGrid, P: np.ndarray, valid: np.ndarray) -> list[tuple[np.ndarray, ...]]:
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
            while small.shape[0] > h:
                small = cv2.resize(small, (small.shape[1] // 2, small.shape[0] // 2), interpolation=cv2.INTER_LINEAR)
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
    def _point_data(self, grid: DepthGrid, obj: np.ndarray, X, Y, hgt) -> dict:
        """Per object point: grid index, row / column, upright x / y, height, footprint cell and
        footprint blob (connected components of the closed occupancy) -- shared by all
        segmentations."""
        cfg = self.config
        h, w = obj.shape
        idx = np.flatnonzero(obj)
        gv, gu = np.divmod(idx, w)
        xs, ys, hs = X.ravel()[idx], Y.ravel()[idx], hgt.ravel()[idx]
        x0, y0 = float(xs.min()), float(ys.min())
        cx = np.minimum(((xs - x0) / cfg.cell).astype(np.int64), 1023)
        cy = np.minimum(((ys - y0) / cfg.cell).astype(np.int64), 1023)
        CW = int(cx.max()) + 1
        CH = int(cy.max()) + 1
        cell = cy * CW + cx
        occ = np.zeros(CW * CH, np.uint8)
        occ[cell] = 1
        occ = cv2.dilate(occ.reshape(CH, CW), np.ones((3, 3), np.uint8))
        _, blab = cv2.connectedComponents(occ, connectivity=8, ltype=cv2.CV_32S)
        V = np.stack([hs, gu, gv, xs, ys], axis=1).astype(np.float64)
        return dict(idx=idx, cell=cell, blob=blab.ravel()[cell], V=V, grid_shape=(CH, CW))

    def _hypotheses(self, grid, pd: dict, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Candidate boxes (n,4), scores (n,) and kinds of one segmentation (not deduplicated)."""
        cfg = self.config
        s = grid.stride
        H, W = grid.image_shape
        sid = seg.ravel()[pd["idx"]].astype(np.int64) - 1  # CC labels of object nodes: 1..S
        if len(sid) == 0:
            return np.zeros((0, 4)), np.zeros((0, _NF)), []
        S = int(sid.max()) + 1
        cell = pd["cell"]
        # per-segment statistics
        npts = np.bincount(sid, minlength=S)
        if npts.min() == 0:  # (labels are contiguous; guard anyway)
            uniq, sid = np.unique(sid, return_inverse=True)
            S = len(uniq)
            npts = np.bincount(sid, minlength=S)

        # per-segment min / max of (height, col, row, x, y): one sort, two reduceat calls
        order = np.argsort(sid, kind="stable")
        starts = np.searchsorted(sid[order], np.arange(S))
        V = pd["V"][order]
        mins = np.minimum.reduceat(V, starts, axis=0)
        maxs = np.maximum.reduceat(V, starts, axis=0)
        hmin, umin, vmin, xmin, ymin = mins.T
        hmax, umax, vmax, xmax, ymax = maxs.T
        # footprint overlap between segments: pairs sharing a footprint cell
        key = np.unique(cell * S + sid)
        kc, ks = np.divmod(key, S)
        area = np.bincount(ks, minlength=S).astype(np.float64)
        pa, pb = [], []
        for k in range(1, 6):
            same = kc[k:] == kc[:-k]
            if not same.any():
                break
            pa.append(ks[:-k][same])
            pb.append(ks[k:][same])
        if pa:
            pk, shared = np.unique(np.concatenate(pa) * S + np.concatenate(pb), return_counts=True)
            p1, p2 = np.divmod(pk, S)
            I = np.concatenate([p1, p2])  # container candidates
            J = np.concatenate([p2, p1])
            sh = np.concatenate([shared, shared]).astype(np.float64)
            inside = sh >= cfg.contain_frac * area[J]  # J mostly inside I's footprint
            I, J = I[inside], J[inside]
        else:
            I = J = np.zeros(0, np.int64)
        below = hmax[J] <= hmin[I] + cfg.below_margin

        # stats columns: umin vmin umax vmax xmin ymin xmax ymax hmax (max ones negated -> all mins)
        AT = np.stack([umin, vmin, -umax, -vmax, xmin, ymin, -xmax, -ymax, -hmax, hmin], axis=1)
        sign = _SIGN

        def union_rows(Ii, Jj):
            """Per segment i: union of i and the segments j of the pairs (i, j)."""
            out = AT.copy()
            np.minimum.at(out, Ii, AT[Jj])
            n = npts.astype(np.int64).copy()
            np.add.at(n, Ii, npts[Jj])
            return out * sign, n

        def union_labels(lab):
            """Union per label of ``lab`` (S,): (stats rows, counts) of the distinct labels."""
            L = int(lab.max()) + 1
            out = np.full((L, 10), np.inf)
            np.minimum.at(out, lab, AT)
            n = np.bincount(lab, weights=npts, minlength=L)
            u = np.unique(lab)
            return out[u] * sign, n[u]

        seed = np.flatnonzero(npts >= cfg.min_points)
        parts = []  # (stats (m, 9), npts (m,), score, kind)
        st, n = union_rows(I[below], J[below])
        parts.append((st[seed], n[seed], 0.9, "core"))
        st, n = union_rows(I, J)
        parts.append((st[seed], n[seed], 0.8, "stack"))
        # groups: connected components of the "inside" relation
        st, n = union_labels(_components(S, I, J))
        parts.append((st, n, 0.7, "group"))
        # blobs: connected components of the closed footprint occupancy
        segblob = np.zeros(S, np.int64)
        segblob[sid] = pd["blob"]
        st, n = union_labels(segblob)
        parts.append((st, n, 0.6, "blob"))
        if cfg.split_length > 0:
            parts.extend(self._equal_splits(pd, sid, S, npts, xmin, xmax, ymin, ymax))
        return self._finalize(grid, parts)

    def _equal_splits(self, pd: dict, sid, S, npts, xmin, xmax, ymin, ymax) -> list:
        """Long segments (a row of equal dressers / night stands, fronts flush, same
        material) cut into 2 or 3 equal parts along their footprint's main axis; parts and
        neighbouring pairs become hypotheses."""
        cfg = self.config
        diag = np.hypot(xmax - xmin, ymax - ymin)
        cand = np.flatnonzero((diag > cfg.split_length) & (npts >= 30))
        if cand.size == 0:
            return []
        cand = cand[np.argsort(-npts[cand])][: cfg.split_max_segments]
        V = pd["V"]
        out = []
        sign = _SIGN
        for i in cand:
            Vi = V[sid == i]
            xy = Vi[:, 3:5] - Vi[:, 3:5].mean(0)
            cxx, cxy, cyy = (xy[:, 0] ** 2).mean(), (xy[:, 0] * xy[:, 1]).mean(), (xy[:, 1] ** 2).mean()
            a = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
            t = xy[:, 0] * np.cos(a) + xy[:, 1] * np.sin(a)
            o = np.argsort(t)
            ts, Vs = t[o], Vi[o]
            m = len(ts)
            lo, hi = ts[int(0.02 * (m - 1))], ts[int(0.98 * (m - 1))]
            for k in (2, 3):
                if (hi - lo) / k < 0.35:
                    continue
                starts = np.r_[0, np.searchsorted(ts, lo + (hi - lo) * np.arange(1, k) / k)]
                if np.any(np.diff(np.r_[starts, m]) <= 0):
                    continue
                mins = np.minimum.reduceat(Vs, starts, axis=0)
                maxs = np.maximum.reduceat(Vs, starts, axis=0)
                st = np.stack([mins[:, 1], mins[:, 2], maxs[:, 1], maxs[:, 2], mins[:, 3], mins[:, 4],
                               maxs[:, 3], maxs[:, 4], maxs[:, 0], mins[:, 0]], 1)
                n = np.diff(np.r_[starts, m])
                out.append((st, n, 0.55, f"split{k}"))
                if k == 3:  # neighbouring pairs
                    pair = np.minimum(st[:-1] * sign, st[1:] * sign) * sign
                    out.append((pair, n[:-1] + n[1:], 0.5, "split3p"))
        return out

    def _finalize(self, grid, parts) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Pixel boxes, ranking features (see :func:`_features`) and kinds of hypothesis
        stats rows (umin vmin umax vmax xmin ymin xmax ymax hmax hmin, grid / upright
        units); drops tiny, flat and oversized ones."""
        cfg = self.config
        s = grid.stride
        H, W = grid.image_shape
        parts = [p for p in parts if len(p[0])]
        if not parts:
            return np.zeros((0, 4)), np.zeros((0, _NF)), []
        stats = np.concatenate([p[0] for p in parts])
        npt = np.concatenate([p[1] for p in parts])
        kinds = [p[3] for p in parts for _ in range(len(p[0]))]
        ext = np.maximum(stats[:, 6] - stats[:, 4], stats[:, 7] - stats[:, 5])
        pad = cfg.pad_px
        boxes = np.stack(
            [
                stats[:, 0] * s - pad,
                stats[:, 1] * s - pad,
                (stats[:, 2] + 1) * s + pad,
                (stats[:, 3] + 1) * s + pad + cfg.pad_bottom_px,
            ],
            1,
        )
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, W)
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, H)
        ok = (
            (npt >= cfg.min_points)
            & (stats[:, 8] >= cfg.min_height)
            & (ext <= cfg.max_extent)
            & (boxes[:, 2] - boxes[:, 0] >= cfg.min_box_px)
            & (boxes[:, 3] - boxes[:, 1] >= cfg.min_box_px)
        )
        sel = np.flatnonzero(ok)
        kinds = [kinds[i] for i in sel]
        return boxes[sel], _features(stats[sel], npt[sel], boxes[sel], kinds, W, H), kinds

    def _layers(self, grid, pd: dict) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Footprint blobs split at steps of the top-height map: touching furniture of
        different heights (a night stand beside a dresser, fronts flush) becomes separate."""
        cfg = self.config
        CH, CW = pd["grid_shape"]
        cell = pd["cell"]
        hs = pd["V"][:, 0]
        hm = np.full(CH * CW, -1.0, np.float32)
        np.maximum.at(hm, cell, hs.astype(np.float32))
        hm = hm.reshape(CH, CW)
        occ = hm >= 0
        # close one-cell gaps (sparse far points) with the neighbours' top height
        hd = cv2.dilate(hm, np.ones((3, 3), np.uint8))
        hf = np.where(occ, hm, hd)
        occf = hf >= 0
        step = cfg.layer_step
        img = np.zeros((2 * CH - 1, 2 * CW - 1), np.uint8)
        img[::2, ::2] = occf
        img[::2, 1::2] = occf[:, :-1] & occf[:, 1:] & (np.abs(hf[:, 1:] - hf[:, :-1]) <= step)
        img[1::2, ::2] = occf[:-1, :] & occf[1:, :] & (np.abs(hf[1:, :] - hf[:-1, :]) <= step)
        _, lab = cv2.connectedComponents(img, connectivity=4, ltype=cv2.CV_32S)
        clab = lab[::2, ::2]
        plab = clab.ravel()[cell]
        st, n = _label_stats(pd["V"], plab)
        parts = [(st, n, 0.75, "layer")]
        # pairs of layers meeting at a step (a chair's back and seat, a bed and its headboard)
        ul = np.unique(plab)
        pos = np.full(int(clab.max()) + 1, -1, np.int64)
        pos[ul] = np.arange(len(ul))
        pairs = []
        for a, b in ((clab[:, :-1], clab[:, 1:]), (clab[:-1, :], clab[1:, :])):
            m = (a > 0) & (b > 0) & (a != b)
            pairs.append(np.stack([np.minimum(a[m], b[m]), np.maximum(a[m], b[m])], 1))
        pr = np.concatenate(pairs).astype(np.int64)
        if len(pr):
            big = int(pr.max()) + 1
            pk = np.unique(pr[:, 0] * big + pr[:, 1])
            pr = np.stack([pk // big, pk % big], 1)
            i, j = pos[pr[:, 0]], pos[pr[:, 1]]
            okp = (i >= 0) & (j >= 0)
            i, j = i[okp], j[okp]
            st2 = np.minimum(st[i] * _SIGN, st[j] * _SIGN) * _SIGN
            parts.append((st2, n[i] + n[j], 0.65, "layer2"))
        return self._finalize(grid, parts)


# ---------------------------------------------------------------------------------------


KINDS = ("core", "stack", "group", "blob", "layer", "layer2", "split2", "split3", "split3p")
_NF = 1 + len(KINDS) + 9  # bias, kind one-hot, geometry (see _features); + consensus in propose

def rank_features(F: np.ndarray) -> np.ndarray:
    """Design matrix of the quadratic logistic ranking: ``F`` (n, _NF + 1: :func:`_features`
    plus the consensus column) followed by the pairwise products (with squares) of its
    geometry and consensus columns -- (n, _NF + 1 + 55)."""
    g = F[:, 1 + len(KINDS):]
    iu = np.triu_indices(g.shape[1])
    return np.concatenate([F, (g[:, :, None] * g[:, None, :])[:, iu[0], iu[1]]], 1)


#: quadratic logistic ranking weights (objectness of a hypothesis) over
#: :func:`rank_features`: bias, kinds (core stack group blob layer layer2 split2 split3
#: split3p), log points, top, bottom, max / min footprint extent, log area share, log
#: aspect, border, size-plausible, consensus, then their pairwise products. Each object's
#: matching hypotheses share one unit of weight, so small objects with few hypotheses rank
#: as well as large ones with many. Fitted on the first 500 training frames with
#: ``python -m shape_detector.proposals.evaluate --fit-ranker --data data/train --frames 500``.
_RANK_W = np.array(
    [
        -0.9706, 0.2524, 0.1810, 0.5613, -0.1862, -0.3127, 0.1317, -0.5647, -0.8060, -0.2273,
        -0.4145, 0.8584, -1.0861, 0.8367, 0.9020, 1.1539, -0.1817, 0.3368, 0.4969, 0.2122, 0.0197,
        1.0294, -0.4644, 0.5314, 0.3286, 0.9418, -0.0201, -0.2194, 0.9067, 0.3210, -0.8438, -0.6443,
        -0.7509, -0.3222, -0.9108, 0.3782, -0.1989, 0.2808, -0.1737, -0.6004, 0.0087, 0.0793,
        0.9935, -0.6488, 0.3883, -0.6172, 0.1728, -0.3287, -0.0036, -0.9469, -0.1433, -0.2021,
        -0.7712, -0.1274, -0.0064, -1.0677, 0.4925, -0.1107, -0.4951, 0.0797, -1.1877, 0.1703,
        0.3288, -0.3643, 0.0104, -1.1959, -0.3092, -0.2135, -0.2126, 0.3368, -0.1332, -0.2456,
        0.4969, 0.3936, -0.1150,
    ]
)


def _features(stats: np.ndarray, npts: np.ndarray, boxes: np.ndarray, kinds: list[str], W: int, H: int) -> np.ndarray:
    """Ranking features (n, _NF) of hypotheses: bias, kind one-hot, log points, top and
    bottom height above the floor, footprint max / min extent, log box area share, log
    aspect, touches the image border, furniture-size plausibility."""
    n = len(stats)
    f = np.zeros((n, _NF))
    f[:, 0] = 1.0
    kid = {k: i for i, k in enumerate(KINDS)}
    f[np.arange(n), 1 + np.array([kid[k] for k in kinds], np.int64)] = 1.0
    g = 1 + len(KINDS)
    ex = stats[:, 6] - stats[:, 4]
    ey = stats[:, 7] - stats[:, 5]
    top, bot = stats[:, 8], stats[:, 9]
    emax, emin = np.maximum(ex, ey), np.minimum(ex, ey)
    bw = np.maximum(boxes[:, 2] - boxes[:, 0], 1.0)
    bh = np.maximum(boxes[:, 3] - boxes[:, 1], 1.0)
    f[:, g + 0] = np.log(np.maximum(npts, 1)) / 5.0
    f[:, g + 1] = np.clip(top, 0, 3)
    f[:, g + 2] = np.clip(bot, -0.2, 1.5)
    f[:, g + 3] = np.clip(emax, 0, 5)
    f[:, g + 4] = np.clip(emin, 0, 5)
    f[:, g + 5] = np.log(bw * bh / (W * H)) / 5.0
    f[:, g + 6] = np.log(bh / bw)
    f[:, g + 7] = ((boxes[:, 0] <= 0) | (boxes[:, 1] <= 0) | (boxes[:, 2] >= W) | (boxes[:, 3] >= H)).astype(float)
    size_ok = (top >= 0.35) & (top <= 2.3) & (emax >= 0.3) & (emax <= 3.0) & (emin <= 2.0)
    f[:, g + 8] = size_ok.astype(float)
    return f


def _label_stats(V: np.ndarray, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct label of points: stats rows (umin vmin umax vmax xmin ymin xmax ymax
    hmax hmin) from ``V`` (n, 5) = (height, col, row, x, y), and point counts."""
    order = np.argsort(lab, kind="stable")
    ls = lab[order]
    starts = np.flatnonzero(np.r_[True, ls[1:] != ls[:-1]])
    Vs = V[order]
    mins = np.minimum.reduceat(Vs, starts, axis=0)
    maxs = np.maximum.reduceat(Vs, starts, axis=0)
    n = np.diff(np.r_[starts, len(ls)])
    st = np.stack(
        [mins[:, 1], mins[:, 2], maxs[:, 1], maxs[:, 2], mins[:, 3], mins[:, 4],
         maxs[:, 3], maxs[:, 4], maxs[:, 0], mins[:, 0]],
        1,
    )
    return st, n


def _masked_quantiles(
    V: np.ndarray, M: np.ndarray, qlo: float, qhi: float, bin_w: float, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Approximate ``qlo`` / ``qhi`` quantiles (histogram, ``bin_w`` bins over [lo, hi]) of
    each row of ``V`` (K, n) restricted to the row's mask ``M`` (K, n)."""
    K = V.shape[0]
    nb = int(np.ceil((hi - lo) / bin_w))
    idx = np.clip(((V - lo) / bin_w).astype(np.int64), 0, nb - 1)
    rows = np.broadcast_to(np.arange(K)[:, None], idx.shape)
    hist = np.bincount((rows * nb + idx)[M], minlength=K * nb).reshape(K, nb)
    cum = np.cumsum(hist, axis=1)
    tot = np.maximum(cum[:, -1:], 1)
    i_lo = np.argmax(cum >= qlo * tot, axis=1)
    i_hi = np.argmax(cum >= qhi * tot, axis=1)
    return lo + i_lo * bin_w, lo + (i_hi + 1) * bin_w


def _components(n: int, I: np.ndarray, J: np.ndarray) -> np.ndarray:
    """Connected-component label (smallest member index) of ``n`` nodes with edges (I, J)."""
    lab = np.arange(n)
    if len(I) == 0:
        return lab
    for _ in range(64):
        m = np.minimum(lab[I], lab[J])
        new = lab.copy()
        np.minimum.at(new, I, m)
        np.minimum.at(new, J, m)
        new = new[new]  # pointer jumping
        if np.array_equal(new, lab):
            break
        lab = new
    return lab


def _iou_matrix(boxes: np.ndarray) -> np.ndarray:
    """Pairwise IoU (n, n) of pixel-edge boxes (n, 4)."""
    x1, y1, x2, y2 = boxes.T
    ix = np.clip(np.minimum(x2[:, None], x2[None, :]) - np.maximum(x1[:, None], x1[None, :]), 0, None)
    iy = np.clip(np.minimum(y2[:, None], y2[None, :]) - np.maximum(y1[:, None], y1[None, :]), 0, None)
    inter = ix * iy
    area = (x2 - x1) * (y2 - y1)
    return inter / np.maximum(area[:, None] + area[None, :] - inter, 1e-9)


def _dedup(boxes: np.ndarray, thr: float, iou: np.ndarray | None = None, limit: int | None = None) -> list[int]:
    """Greedy: indices of boxes (in order) not overlapping an earlier kept box by IoU > thr
    (at most ``limit``)."""
    n = len(boxes)
    if n == 0:
        return []
    if iou is None:
        iou = _iou_matrix(boxes)
    limit = n if limit is None else limit
    suppressed = np.zeros(n, bool)
    keep: list[int] = []
    i = 0
    while len(keep) < limit:
        rest = np.flatnonzero(~suppressed[i:])
        if rest.size == 0:
            break
        i += int(rest[0])
        keep.append(i)
        suppressed |= iou[i] > thr
        suppressed[i] = True
    return keep

