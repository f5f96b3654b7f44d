"""Hybrid 2D proposals: the learned network decides *which* objects, the geometric
proposer *where* their edges are.

The learned proposer (:mod:`.learned`) finds more objects than the geometric one
(partly seen chairs behind tables, objects at the image border), but its boxes are
regressed on a 16-pixel grid and are loose; the geometric proposer's boxes come from the
depth segments and are tight where it finds the object at all. Each learned box that a
geometric box overlaps by at least ``match_iou`` takes the geometric box's edges and
keeps the learned score; learned boxes without such a partner stay as they are;
geometric boxes no learned box claimed follow, their scores times ``unmatched_scale``,
or are left out when ``keep_unmatched`` is False.

Boxes are ``(x1, y1, x2, y2)`` pixel edges.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ..box_iou import box2d_iou_matrix
from . import Proposal


def fuse(learned: list[Proposal], geometric: list[Proposal], match_iou: float = 0.5,
         keep_unmatched: bool = True, unmatched_scale: float = 0.9) -> list[Proposal]:
    """The fused proposals, best first (see the module docstring). Each geometric box
    serves at most one learned box: the best-scoring learned box takes its best partner
    first."""
    out: list[Proposal] = []
    used = np.zeros(len(geometric), dtype=bool)
    iou = box2d_iou_matrix([p.box2d for p in learned], [p.box2d for p in geometric])
    for i in np.argsort([-p.score for p in learned], kind="stable"):
        row = np.where(used, -1.0, iou[i])
        j = int(np.argmax(row)) if len(row) else -1
        if j >= 0 and row[j] >= match_iou:
            used[j] = True
            out.append(Proposal(geometric[j].box2d, learned[i].class_name, learned[i].score, "hybrid"))
        else:
            out.append(learned[i])
    if keep_unmatched:
        out.extend(Proposal(g.box2d, g.class_name, g.score * unmatched_scale, g.source)
                   for g, u in zip(geometric, used) if not u)
    return sorted(out, key=lambda p: -p.score)


class HybridProposer:
    """Learned and geometric proposals fused by :func:`fuse`; gravity from the geometric
    proposer. Called like the other proposers: ``(depth, K, up=, rgb=)``.

    The learned network runs in a thread of its own while the geometric proposer runs in
    the caller's: ONNX Runtime and most of OpenCV and numpy release the GIL, so on two
    cores the frame waits for the slower of the two rather than for both."""

    def __init__(self, learned: Any, geometric: Any, match_iou: float = 0.5, keep_unmatched: bool = True,
                 unmatched_scale: float = 0.9) -> None:
        self.learned = learned
        self.geometric = geometric
        self.match_iou = float(match_iou)
        self.keep_unmatched = bool(keep_unmatched)
        self.unmatched_scale = float(unmatched_scale)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0

    def __call__(self, depth: np.ndarray, K: np.ndarray, up: np.ndarray | None = None,
                 rgb: np.ndarray | None = None) -> tuple[Any, list[Proposal]]:
        """``(GravityEstimate, proposals)``; needs ``rgb``. ``learned`` is a
        :class:`~.learned.LearnedProposer` (its ``detect(rgb, depth)``), ``geometric`` a
        :class:`~.geometric.GeometricProposer` (called as ``(depth, K, up=, rgb=)``)."""
        if rgb is None:
            raise ValueError("the hybrid proposer needs the RGB frame")
        if self._pool is None or self._pool_pid != os.getpid():  # a forked child has no pool thread
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="learned-proposer")
            self._pool_pid = os.getpid()
        pending = self._pool.submit(self.learned.detect, rgb, depth)
        try:
            grav, geo = self.geometric(depth, K, up=up, rgb=rgb)
        finally:
            learned = pending.result()
        return grav, fuse(learned, geo, self.match_iou, self.keep_unmatched, self.unmatched_scale)
