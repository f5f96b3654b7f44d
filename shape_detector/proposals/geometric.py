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

import numpy as np

from ..geometry import upright_rotation
from ..gravity import DepthGrid, GravityConfig, GravityEstimate, auto_stride, estimate_floor_along, estimate_up, make_grid
from . import Proposal
from .geo_hypotheses import HypothesisBuilder
from .geo_ranking import _RANK_W, KINDS, _dedup, _iou_matrix, rank_features
from .geo_segments import Segmenter
from .geo_walls import WallFinder

__all__ = ["GeometricConfig", "GeometricProposer", "KINDS", "ProposalDebug", "rank_features"]


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


class GeometricProposer(WallFinder, Segmenter, HypothesisBuilder):
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
        """Gravity (estimated, or the floor measured along the given ``up``) and the proposals."""
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
        """Proposals (best first) of a strided back-projection ``grid`` under ``grav``."""
        cfg = self.config
        dbg = ProposalDebug(grid=grid)
        self.debug = dbg
        h, w = grid.shape
        P = grid.points
        valid = grid.valid
        R = upright_rotation(grav.up)
        # invalid points (NaN) -> 0 by a masked store: a broadcast np.where is several times slower
        Pf = np.array(P, dtype=np.float32)
        Pf[~valid] = 0.0
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
            wtol = cfg.wall_tol + 0.003 * z * z  # on-wall tolerance (m), the same for every wall
            for nrm, rho in walls:
                off = X * nrm[0] + Y * nrm[1] - rho
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
