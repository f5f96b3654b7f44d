"""Ranking of the geometric proposer's candidates: features, the fitted quadratic logistic
weights, pairwise IoU and greedy de-duplication."""

from __future__ import annotations

import numpy as np

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
        rest = suppressed[i:]
        j = int(rest.argmin())  # first box not suppressed (argmin of bools: first False)
        if rest[j]:
            break
        i += j
        keep.append(i)
        np.logical_or(suppressed, iou[i] > thr, out=suppressed)
        suppressed[i] = True
    return keep
