"""Fast paths of the geometric proposer and the depth grid against their plain numpy
definitions: radix sorts, sort-based unique, block reductions, greedy de-duplication,
and grids that later calls leave untouched (reused work buffers)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from shape_detector.gravity import make_grid
from shape_detector.gravity_grid import _block_reduce
from shape_detector.proposals.evaluate import VGA_K
from shape_detector.proposals.geo_hypotheses import _sorted_unique, _stable_order
from shape_detector.proposals.geo_ranking import _dedup, _iou_matrix


@pytest.mark.parametrize("hi", [1, 300, 65536, 70000])
def test_stable_order_is_stable_argsort(hi: int) -> None:
    rng = np.random.default_rng(hi)
    for lo in (0, -5):
        lab = rng.integers(lo, hi, 5000)
        assert np.array_equal(_stable_order(lab), np.argsort(lab, kind="stable"))
    assert _stable_order(np.zeros(0, np.int64)).size == 0


@pytest.mark.parametrize("hi", [50, 1 << 20, (1 << 32) - 1, 1 << 40])
def test_sorted_unique_is_unique_with_counts(hi: int) -> None:
    rng = np.random.default_rng(7)
    for lo in (0, -hi):
        a = rng.integers(lo, hi, 4000)
        a[:10] = hi - 1  # the largest key present
        u, c = _sorted_unique(a)
        ru, rc = np.unique(a, return_counts=True)
        assert np.array_equal(u, ru) and np.array_equal(c, rc)
    u, c = _sorted_unique(np.zeros(0, np.int64))
    assert u.size == 0 and c.size == 0


@pytest.mark.parametrize("s", [1, 2, 3, 4, 5])
def test_block_reduce_matches_reshape(s: int) -> None:
    rng = np.random.default_rng(s)
    a = rng.random((6 * s, 7 * s)).astype(np.float32)
    blocks = a.reshape(6, s, 7, s)
    assert np.array_equal(_block_reduce(a, s, np.minimum), blocks.min(axis=(1, 3)))
    assert np.array_equal(_block_reduce(a, s, np.maximum), blocks.max(axis=(1, 3)))


def _dedup_reference(boxes: np.ndarray, thr: float, limit: int) -> list[int]:
    iou = _iou_matrix(boxes)
    keep: list[int] = []
    for i in range(len(boxes)):
        if len(keep) >= limit:
            break
        if all(iou[i, k] <= thr for k in keep):
            keep.append(i)
    return keep


def test_dedup_matches_greedy_reference() -> None:
    rng = np.random.default_rng(3)
    for n in (0, 1, 5, 60):
        xy = rng.uniform(0, 100, (n, 2))
        wh = rng.uniform(5, 40, (n, 2))
        boxes = np.round(np.concatenate([xy, xy + wh], 1))
        for thr, limit in ((0.5, 100), (0.9, 30), (0.3, 4)):
            assert _dedup(boxes, thr, None, limit) == _dedup_reference(boxes, thr, limit)


def test_grids_survive_later_calls() -> None:
    """Work buffers are reused across calls; no returned array may share them."""
    rng = np.random.default_rng(0)
    fields = ["points", "valid", "pmean", "normals", "nvalid", "u", "v", "rnormals", "rvalid"]
    depth = (1.0 + rng.random((480, 640)) * 3.0).astype(np.float32)
    depth[100:140, 200:260] = np.nan
    g1 = make_grid(depth, VGA_K, stride=4)
    snap = copy.deepcopy(g1)
    make_grid(depth[::-1].copy() * 1.5, VGA_K, stride=4)
    for f in fields:
        assert np.array_equal(getattr(g1, f), getattr(snap, f), equal_nan=True), f
