"""Per-class primitive anchors: class templates from GT parts, raw-value inversion, network use."""

from __future__ import annotations

import numpy as np
import torch

from shape_detector.model.config import ModelConfig
from shape_detector.model.network import FrustumShapeNet
from shape_detector.model.primitives import primitive_params
from shape_detector.model.shape_anchors import class_templates, medoid_template, relative_parts, templates_to_raw


def _table(top: float = 0.04, leg: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Box-relative bounds of a unit-cube table: a top slab and four corner legs."""
    lo = [[-0.5, -0.5, 0.5 - top]]
    hi = [[0.5, 0.5, 0.5]]
    for x in (-0.5, 0.5 - leg):
        for y in (-0.5, 0.5 - leg):
            lo.append([x, y, -0.5])
            hi.append([x + leg, y + leg, 0.5 - top])
    return np.array(lo), np.array(hi)


def test_relative_parts_scales_per_axis_and_bounds_rotated_parts():
    c = np.array([[0.5, 0.0, 0.25]])
    s = np.array([[1.0, 0.2, 0.5]])
    R = np.eye(3)[None]
    lo, hi = relative_parts(c, s, R, np.array([2.0, 1.0, 1.0]))
    np.testing.assert_allclose(lo, [[0.0, -0.1, 0.0]])
    np.testing.assert_allclose(hi, [[0.5, 0.1, 0.5]])
    Rz = np.array([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])  # 90 deg about z: x <-> y extents
    lo, hi = relative_parts(np.zeros((1, 3)), s, Rz, np.ones(3))
    np.testing.assert_allclose(hi - lo, [[0.2, 1.0, 0.5]])


def test_medoid_is_the_typical_object_and_small_objects_are_split_not_repeated():
    table, block = _table(), (np.array([[-0.5, -0.5, -0.5]]), np.array([[0.5, 0.5, 0.5]]))
    lo, hi, iou = medoid_template([table, table, _table(0.05, 0.06), block], 5)
    np.testing.assert_allclose(lo, table[0][np.argsort(-np.prod(table[1] - table[0], 1))])  # top first, then legs
    assert 0.5 < iou < 1.0
    # one part, three slots: the block is split along its longest side, the union unchanged
    lo, hi, _ = medoid_template([block], 3)
    assert len(lo) == 3 and len({tuple(r) for r in np.round(np.c_[lo, hi], 6)}) == 3
    assert np.isclose(np.prod(hi - lo, 1).sum(), 1.0)
    np.testing.assert_allclose(lo.min(0), -0.5)
    np.testing.assert_allclose(hi.max(0), 0.5)


def test_class_templates_from_dataset_arrays():
    lo_t, hi_t = _table()
    box = np.array([1.2, 0.8, 0.75])
    P = 8
    pc, ps = np.zeros((3, P, 3)), np.zeros((3, P, 3))
    pr = np.tile(np.eye(3), (3, P, 1, 1))
    for r in range(3):
        pc[r, :5], ps[r, :5] = 0.5 * (lo_t + hi_t) * box, (hi_t - lo_t) * box
    lo, hi, found = class_templates(pc, ps, pr, np.array([5, 5, 0]), np.tile(box, (3, 1)), np.array([1, 1, 2]), 4, 5)
    assert found.tolist() == [False, True, False, False]  # class 2's only row has no parts
    np.testing.assert_allclose(np.sort(lo[1], 0), np.sort(lo_t, 0), atol=1e-6)
    assert np.all(lo[0] == 0) and np.all(hi[0] == 0)


def test_templates_to_raw_inverts_the_primitive_mapping():
    lo, hi = _table()
    raw = torch.tensor(templates_to_raw(lo, hi, 0.01), dtype=torch.float64)[None]
    box = torch.tensor([[1.6, 0.9, 0.74]], dtype=torch.float64)
    p = primitive_params(raw, box, 0.01)
    np.testing.assert_allclose(p["center"][0].numpy(), 0.5 * (lo + hi) * box.numpy(), atol=1e-9)
    # sizes are exact down to the clip that keeps the raw values finite (1e-3 of the box)
    np.testing.assert_allclose(p["size"][0].numpy(), (hi - lo) * box.numpy(), atol=2e-3)
    np.testing.assert_allclose(p["rotation"][0].numpy(), np.tile(np.eye(3), (5, 1, 1)), atol=1e-12)


def test_network_adds_the_given_or_predicted_class_anchor():
    torch.manual_seed(0)
    cfg = ModelConfig(num_points=64, num_object_points=32, seg_widths=(8, 8, 16), seg_head_widths=(8,),
                      tnet_widths=(8, 16), tnet_fc=(8,), box_widths=(8, 16), box_fc=(16,), shape_fc=(16,),
                      shape_widths=(8, 16), cls_fc=(8,), shape_anchors=True)
    net = FrustumShapeNet(cfg).eval()
    with torch.no_grad():
        net.shape_head.out.weight.zero_()
        net.shape_head.out.bias.zero_()
        net.shape_anchor.copy_(torch.arange(cfg.num_classes, dtype=torch.float32)[:, None].expand_as(net.shape_anchor))
    pts = torch.randn(3, 64, 6)
    oh = torch.zeros(3, cfg.num_classes)
    oh[0, 4] = 1.0  # given class 4; rows 1, 2: the class head decides
    with torch.no_grad():
        out = net(pts, oh)
    raw = out["shape_raw"]
    assert torch.all(raw[0] == 4.0)
    pred = out["cls_logits"][1:, : cfg.num_classes].argmax(1).float()
    assert torch.all(raw[1:].flatten(1)[:, 0] == pred)  # an anchor is selected, not computed
    assert FrustumShapeNet(ModelConfig(shape_anchors=False)).shape_anchor is None
