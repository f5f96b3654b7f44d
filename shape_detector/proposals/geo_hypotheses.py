"""Hypotheses of the geometric proposer: gravity-aware groupings of segments on the floor
footprint grid (core, stack, group, blob, splits, layers) as scored candidate boxes."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..gravity import DepthGrid
from .geo_ranking import _NF, _features

if TYPE_CHECKING:
    from .geometric import GeometricConfig, ProposalDebug

#: stats rows: umin vmin umax vmax xmin ymin xmax ymax hmax hmin; sign turning all into minima
_SIGN = np.array([1, 1, -1, -1, 1, 1, -1, -1, -1, 1], np.float64)
#: columns of ``[mins | maxs]`` of (height, col, row, x, y) in stats-row order
_STATS_COLS = np.array([1, 2, 6, 7, 3, 4, 8, 9, 5, 0], np.int64)


def _stats_rows(mins: np.ndarray, maxs: np.ndarray) -> np.ndarray:
    """Stats rows (umin vmin umax vmax xmin ymin xmax ymax hmax hmin) from per-group
    minima / maxima (m, 5) of (height, col, row, x, y) -- one gather, no per-column stack."""
    return np.concatenate([mins, maxs], 1)[:, _STATS_COLS]


def _stable_order(lab: np.ndarray) -> np.ndarray:
    """``np.argsort(lab, kind="stable")`` of integer labels; labels in [0, 65536) are sorted
    as uint16, for which numpy uses a radix sort (the same permutation, far faster)."""
    if lab.size and int(lab.min()) >= 0 and int(lab.max()) < 65536:
        return np.argsort(lab.astype(np.uint16), kind="stable")
    return np.argsort(lab, kind="stable")


def _sorted_unique(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a, return_counts=True)`` of a 1D integer array by one sort (cheaper than
    ``np.unique``'s hashing for the few thousand keys of a frame)."""
    if a.size == 0:
        return np.sort(a), np.zeros(0, np.int64)
    if int(a.min()) >= 0 and int(a.max()) < 1 << 32:
        # two stable 16-bit radix passes (low half, then high half) sort 32-bit keys
        # several times faster than np.sort of int64
        o = np.argsort((a & 0xFFFF).astype(np.uint16), kind="stable")
        o = o[np.argsort((a[o] >> 16).astype(np.uint16), kind="stable")]
        s = a[o]
    else:
        s = np.sort(a)
    first = _group_starts(s)
    return s[first], np.diff(np.r_[first, s.size])


def _group_starts(sorted_lab: np.ndarray) -> np.ndarray:
    """Start index of each run of equal values in the sorted labels ``sorted_lab`` (non-empty)."""
    return np.flatnonzero(np.r_[True, sorted_lab[1:] != sorted_lab[:-1]])


def _groups(lab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(order, starts, labels)`` of integer labels ``lab`` (non-empty): the stable order that
    sorts them, where each label's run starts in that order, and the distinct labels
    (ascending) -- for per-label ``reduceat`` over rows taken in ``order``."""
    order = _stable_order(lab)
    ls = lab[order]
    starts = _group_starts(ls)
    return order, starts, ls[starts]


def _containment_pairs(cell: np.ndarray, sid: np.ndarray, S: int, contain_frac: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` of segments (labels ``sid`` 0..S-1 of nodes in footprint cells ``cell``)
    where at least ``contain_frac`` of j's footprint cells are also i's (j mostly inside i's
    footprint), from the segment pairs sharing a footprint cell."""
    key = _sorted_unique(cell * S + sid)[0]
    kc, ks = np.divmod(key, S)
    area = np.bincount(ks, minlength=S).astype(np.float64)
    pa, pb = [], []
    for k in range(1, 6):
        same = kc[k:] == kc[:-k]
        if not same.any():
            break
        pa.append(ks[:-k][same])
        pb.append(ks[k:][same])
    if not pa:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pk, shared = _sorted_unique(np.concatenate(pa) * S + np.concatenate(pb))
    p1, p2 = np.divmod(pk, S)
    ci = np.concatenate([p1, p2])  # container candidates
    cj = np.concatenate([p2, p1])
    sh = np.concatenate([shared, shared]).astype(np.float64)
    inside = sh >= contain_frac * area[cj]  # cj mostly inside ci's footprint
    return ci[inside], cj[inside]


class HypothesisBuilder:
    """Mixin of :class:`~.geometric.GeometricProposer`: per-point data, hypotheses of a
    segmentation, equal splits, footprint layers and their boxes (uses ``self.config``)."""

    config: GeometricConfig
    debug: ProposalDebug

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
        # columns filled in place: np.stack of mixed dtypes plus a cast costs far more
        V = np.empty((len(idx), 5), np.float64)
        V[:, 0], V[:, 1], V[:, 2], V[:, 3], V[:, 4] = hs, gu, gv, xs, ys
        return dict(idx=idx, cell=cell, blob=blab.ravel()[cell], V=V, grid_shape=(CH, CW))

    def _hypotheses(self, grid, pd: dict, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Candidate boxes (n,4), scores (n,) and kinds of one segmentation (not deduplicated)."""
        cfg = self.config
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
        # (labels 0..S-1 all present: segment i starts after the points of segments < i)
        order = _stable_order(sid)
        starts = np.zeros(S, np.int64)
        np.cumsum(npts[:-1], out=starts[1:])
        V = np.take(pd["V"], order, axis=0)
        mins = np.minimum.reduceat(V, starts, axis=0)
        maxs = np.maximum.reduceat(V, starts, axis=0)
        hmin, umin, vmin, xmin, ymin = mins.T
        hmax, umax, vmax, xmax, ymax = maxs.T
        # footprint overlap between segments: pairs sharing a footprint cell
        ci, cj = _containment_pairs(cell, sid, S, cfg.contain_frac)
        below = hmax[cj] <= hmin[ci] + cfg.below_margin

        # stats columns: umin vmin umax vmax xmin ymin xmax ymax hmax (max ones negated -> all mins)
        AT = _stats_rows(mins, maxs) * _SIGN
        sign = _SIGN

        # unions by sorting and reduceat: np.minimum.at on stats rows is far slower
        def union_rows(Ii, Jj):
            """Per segment i: union of i and the segments j of the pairs (i, j)."""
            out = AT.copy()
            n = npts.astype(np.int64).copy()
            if len(Ii):
                o, first, rows = _groups(Ii)
                Js = Jj[o]
                out[rows] = np.minimum(out[rows], np.minimum.reduceat(np.take(AT, Js, axis=0), first, axis=0))
                n[rows] += np.add.reduceat(npts[Js], first)
            return out * sign, n

        def union_labels(lab):
            """Union per label of ``lab`` (S,): (stats rows, counts) of the distinct labels."""
            L = int(lab.max()) + 1
            o, first, u = _groups(lab)
            out = np.minimum.reduceat(np.take(AT, o, axis=0), first, axis=0)
            n = np.bincount(lab, weights=npts, minlength=L)
            return out * sign, n[u]

        seed = np.flatnonzero(npts >= cfg.min_points)
        parts = []  # (stats (m, 9), npts (m,), score, kind)
        st, n = union_rows(ci[below], cj[below])
        parts.append((st[seed], n[seed], 0.9, "core"))
        st, n = union_rows(ci, cj)
        parts.append((st[seed], n[seed], 0.8, "stack"))
        # groups: connected components of the "inside" relation
        st, n = union_labels(_components(S, ci, cj))
        parts.append((st, n, 0.7, "group"))
        # blobs: connected components of the closed footprint occupancy
        segblob = np.zeros(S, np.int64)
        segblob[sid] = pd["blob"]
        st, n = union_labels(segblob)
        parts.append((st, n, 0.6, "blob"))
        if cfg.split_length > 0:
            parts.extend(self._equal_splits(V, starts, npts, xmin, xmax, ymin, ymax))
        return self._finalize(grid, parts)

    def _equal_splits(self, V_seg: np.ndarray, seg_starts: np.ndarray, npts, xmin, xmax, ymin, ymax) -> list:
        """Long segments (a row of equal dressers / night stands, fronts flush, same
        material) cut into 2 or 3 equal parts along their footprint's main axis; parts and
        neighbouring pairs become hypotheses. ``V_seg``: the points' (height, col, row, x, y)
        stably sorted by segment, ``seg_starts``: each segment's first row there."""
        cfg = self.config
        diag = np.hypot(xmax - xmin, ymax - ymin)
        cand = np.flatnonzero((diag > cfg.split_length) & (npts >= 30))
        if cand.size == 0:
            return []
        cand = cand[np.argsort(-npts[cand])][: cfg.split_max_segments]
        out = []
        sign = _SIGN
        for i in cand:
            Vi = V_seg[seg_starts[i] : seg_starts[i] + npts[i]]  # in point order: the sort is stable
            xy = Vi[:, 3:5] - Vi[:, 3:5].mean(0)
            cxx, cxy, cyy = (xy[:, 0] ** 2).mean(), (xy[:, 0] * xy[:, 1]).mean(), (xy[:, 1] ** 2).mean()
            a = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
            t = xy[:, 0] * np.cos(a) + xy[:, 1] * np.sin(a)
            o = np.argsort(t)
            ts, Vs = t[o], np.take(Vi, o, axis=0)
            m = len(ts)
            lo, hi = ts[int(0.02 * (m - 1))], ts[int(0.98 * (m - 1))]
            for k in (2, 3):
                if (hi - lo) / k < 0.35:
                    continue
                bounds = np.empty(k + 1, np.int64)  # part starts, then the end
                bounds[0], bounds[k] = 0, m
                bounds[1:k] = np.searchsorted(ts, lo + (hi - lo) * np.arange(1, k) / k)
                n = np.diff(bounds)
                if np.any(n <= 0):
                    continue
                starts = bounds[:k]
                st = _stats_rows(np.minimum.reduceat(Vs, starts, axis=0), np.maximum.reduceat(Vs, starts, axis=0))
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
        st, n, ul = _label_groups(pd["V"], plab)
        parts = [(st, n, 0.75, "layer")]
        # pairs of layers meeting at a step (a chair's back and seat, a bed and its headboard)
        pos = np.full(int(clab.max()) + 1, -1, np.int64)
        pos[ul] = np.arange(len(ul))
        pairs = []
        for a, b in ((clab[:, :-1], clab[:, 1:]), (clab[:-1, :], clab[1:, :])):
            m = (a > 0) & (b > 0) & (a != b)
            pairs.append(np.stack([np.minimum(a[m], b[m]), np.maximum(a[m], b[m])], 1))
        pr = np.concatenate(pairs).astype(np.int64)
        if len(pr):
            big = int(pr.max()) + 1
            pk = _sorted_unique(pr[:, 0] * big + pr[:, 1])[0]
            pr = np.stack([pk // big, pk % big], 1)
            i, j = pos[pr[:, 0]], pos[pr[:, 1]]
            okp = (i >= 0) & (j >= 0)
            i, j = i[okp], j[okp]
            st2 = np.minimum(st[i] * _SIGN, st[j] * _SIGN) * _SIGN
            parts.append((st2, n[i] + n[j], 0.65, "layer2"))
        return self._finalize(grid, parts)


# ---------------------------------------------------------------------------------------


def _label_groups(V: np.ndarray, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per distinct label of points: stats rows (umin vmin umax vmax xmin ymin xmax ymax
    hmax hmin) from ``V`` (n, 5) = (height, col, row, x, y), point counts, and the distinct
    labels (ascending)."""
    order, starts, labels = _groups(lab)
    Vs = np.take(V, order, axis=0)
    n = np.diff(np.r_[starts, len(lab)])
    st = _stats_rows(np.minimum.reduceat(Vs, starts, axis=0), np.maximum.reduceat(Vs, starts, axis=0))
    return st, n, labels


def _components(n: int, ci: np.ndarray, cj: np.ndarray) -> np.ndarray:
    """Connected-component label (smallest member index) of ``n`` nodes with edges (ci, cj)."""
    lab = np.arange(n)
    if len(ci) == 0:
        return lab
    for _ in range(64):
        m = np.minimum(lab[ci], lab[cj])
        new = lab.copy()
        np.minimum.at(new, ci, m)
        np.minimum.at(new, cj, m)
        new = new[new]  # pointer jumping
        if np.array_equal(new, lab):
            break
        lab = new
    return lab
