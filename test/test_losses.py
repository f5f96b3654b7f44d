"""Losses: task / weak-supervision masking and a tiny overfit run where every loss drops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from shape_detector.model.config import ModelConfig
from shape_detector.model.losses import compute_losses, huber, parse_tasks
from shape_detector.model.network import FrustumShapeNet
from shape_detector.training import frustum_dataset as fds
from shape_detector.training.train import TensorData, TrainConfig

from test_model_scene import make_frame
from tolerances import outputs_differ




SMALL = dict(num_points=256, num_object_points=128, seg_widths=(32, 32, 64, 128), seg_head_widths=(64, 32),
             tnet_widths=(32, 64), tnet_fc=(64,), box_widths=(32, 64, 128), box_fc=(128, 64), shape_fc=(128,),
             cls_fc=(64,))


def _data(n_frames=3, neg=1):
    frames = [make_frame(s, 2) for s in range(n_frames)]
    ds = fds.build_frustum_dataset(frames, num_points=256, augment_copies=1, rng_seed=0, negatives_per_frame=neg)
    return ds


def test_huber_and_tasks():
    x = torch.tensor([-3.0, -0.5, 0.0, 0.5, 3.0])
    assert torch.allclose(huber(x, 1.0), torch.tensor([2.5, 0.125, 0.0, 0.125, 2.5]))
    assert parse_tasks("box, cls") == {"box", "cls"}
    try:
        parse_tasks("box,foo")
    except ValueError:
        pass
    else:
        raise AssertionError("bad task accepted")


def test_task_flags_and_weak_supervision_masks():
    torch.manual_seed(0)
    ds = _data(2, neg=2)
    data = TensorData(ds, torch.device("cpu"), 10)
    net = FrustumShapeNet(ModelConfig(**SMALL))
    idx = torch.arange(data.n)
    b = data.batch(idx, TrainConfig(), augment=False, one_hot_mode="given")
    out = net(b["points"], b["one_hot"])
    full = compute_losses(out, b, net.mean_sizes, "box,shape,cls")
    assert {"seg", "center", "stage1_center", "corner", "coverage", "consistency", "part", "volume", "cls"} <= set(full)
    det = compute_losses(out, b, net.mean_sizes, "box,cls")
    assert "coverage" not in det and "corner" in det
    shp = compute_losses(out, b, net.mean_sizes, "shape")
    assert "corner" not in shp and "cls" not in shp and "coverage" in shp and "seg" in shp
    # negatives only: seg + cls, no box / shape terms
    neg = b["is_negative"]
    assert bool(neg.any())
    nb = {k: v[neg] for k, v in b.items()}
    no = {k: v[neg] for k, v in out.items()}
    L = compute_losses(no, nb, net.mean_sizes, "box,shape,cls")
    assert set(k for k in L if not k.startswith("stat_")) == {"seg", "cls", "total"}
    # no shape GT -> no shape losses (weak supervision), box losses still there
    pos = ~neg
    pb = {k: v[pos] for k, v in b.items()}
    pb["has_shape"] = torch.zeros_like(pb["has_shape"])
    L = compute_losses({k: v[pos] for k, v in out.items()}, pb, net.mean_sizes, "box,shape,cls")
    assert "coverage" not in L and "corner" in L
    # the shape head gets gradient only from the shape losses
    net.zero_grad()
    det["total"].backward(retain_graph=True)
    assert all(p.grad is None or float(p.grad.abs().sum()) == 0 for p in net.shape_head.parameters())


def test_tiny_overfit_all_losses_decrease():
    torch.manual_seed(0)
    ds = _data(3, neg=1)
    data = TensorData(ds, torch.device("cpu"), 10)
    net = FrustumShapeNet(ModelConfig(**SMALL))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    idx = torch.arange(data.n)
    b = data.batch(idx, TrainConfig(), augment=False, one_hot_mode="given")
    hist = []
    for _ in range(60):
        net.train()
        out = net(b["points"], b["one_hot"])
        L = compute_losses(out, b, net.mean_sizes, "box,shape,cls", l_nearest=1)
        opt.zero_grad()
        L["total"].backward()
        opt.step()
        hist.append({k: float(v.detach()) for k, v in L.items()})
    first = {k: np.mean([h[k] for h in hist[:3]]) for k in hist[0]}
    last = {k: np.mean([h[k] for h in hist[-3:]]) for k in hist[0]}
    assert last["total"] < 0.35 * first["total"], (first["total"], last["total"])
    for k in ("seg", "center", "corner", "size_res", "heading_cls", "coverage", "consistency", "part", "volume", "cls"):
        assert last[k] < first[k], (k, first[k], last[k])


def test_predicted_box_shape_frame_matches_gt_frame_for_a_perfect_box_and_sees_box_errors():
    """shape_frame="predicted_box" compares unit-diagonal frames: with the network's box equal
    to the GT box it gives exactly the GT-frame losses; a box 30% too tall moves the GT parts
    relative to the primitives and changes the losses."""
    ds = _data(2, neg=0)
    data = TensorData(ds, torch.device("cpu"), 10)
    net = FrustumShapeNet(ModelConfig(**SMALL))
    b = data.batch(torch.arange(data.n), TrainConfig(), augment=False, one_hot_mode="given")
    with torch.no_grad():
        out = net(b["points"], b["one_hot"])
    w = dict(occupancy=1.0)
    from shape_detector.model.losses import LossWeights

    def shape_losses(o, frame):
        torch.manual_seed(7)  # the occupancy term draws its sample points
        L = compute_losses(o, b, net.mean_sizes, "shape", LossWeights.from_dict(w), shape_frame=frame)
        return {k: float(L[k]) for k in ("coverage", "consistency", "occupancy")}

    perfect = dict(out, box_size=b["size"].clone())
    ref = shape_losses(perfect, "gt_box")
    same = shape_losses(perfect, "predicted_box")
    for k in ref:
        assert same[k] == pytest.approx(ref[k], rel=1e-4, abs=1e-7), k
    tall = dict(out, box_size=b["size"] * torch.tensor([1.0, 1.0, 1.3]))
    moved = shape_losses(tall, "predicted_box")
    assert any(abs(moved[k] - ref[k]) > 1e-3 * max(ref[k], 1e-6) for k in ref)
    # "both": the mean of the two frames' terms
    torch.manual_seed(7)
    gt_tall = compute_losses(tall, b, net.mean_sizes, "shape", LossWeights.from_dict(w), shape_frame="gt_box")
    torch.manual_seed(7)
    L = compute_losses(tall, b, net.mean_sizes, "shape", LossWeights.from_dict(w), shape_frame="predicted_box")
    torch.manual_seed(7)
    both = compute_losses(tall, b, net.mean_sizes, "shape", LossWeights.from_dict(w), shape_frame="both")
    # coverage is deterministic; consistency and occupancy draw samples, which differ per call
    assert float(both["coverage"]) == pytest.approx(0.5 * (float(gt_tall["coverage"]) + float(L["coverage"])), rel=1e-5)
    for k in ("consistency", "occupancy"):
        assert float(both[k]) == pytest.approx(0.5 * (float(gt_tall[k]) + float(L[k])), rel=0.05), k
    with pytest.raises(ValueError, match="shape_frame"):
        compute_losses(out, b, net.mean_sizes, "shape", shape_frame="camera")


def test_aligned_gt_box_picks_the_quarter_turn_nearest_the_prediction():
    """The GT box (l=2, w=1, heading 0) seen from predictions at 10, 80, 170 and -100 degrees:
    the same solid re-parametrised with its heading within 45 degrees of each prediction,
    length and width swapped after an odd number of quarter turns."""
    from shape_detector.model.losses import aligned_gt_box

    pred = torch.deg2rad(torch.tensor([10.0, 80.0, 170.0, -100.0]))
    gs = torch.tensor([[2.0, 1.0, 0.5]]).repeat(4, 1)
    size, h = aligned_gt_box(pred, gs, torch.zeros(4))
    np.testing.assert_allclose(torch.rad2deg(h).numpy(), [0.0, 90.0, 180.0, -90.0], atol=1e-4)
    np.testing.assert_allclose(size.numpy(), [[2, 1, 0.5], [1, 2, 0.5], [2, 1, 0.5], [1, 2, 0.5]])


def test_second_box_stage_moves_the_box_in_its_own_axes_and_trains_alone():
    """``second_box_stage``'s residuals are in the first box's axes and sizes: a residual of +0.1 box
    lengths along x of a box heading 90 degrees moves the centre +y by 0.1 * l; log size +0.2
    scales every side by e^0.2; the heading residual adds. Its loss terms reach only the second
    stage's parameters, and a few steps on a fixed batch lower them."""
    torch.manual_seed(0)
    net = FrustumShapeNet(ModelConfig(**SMALL, box2_widths=(16, 32), box2_fc=(32,)))
    net.eval()
    B, N = 2, 64
    xyz = torch.randn(B, N, 3)
    fg = torch.rand(B, N) > 0.5
    feat = torch.randn(B, net.box_mlp.out_channels)
    oh = torch.zeros(B, 10)
    c0 = torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.5, 2.0]])
    h0 = torch.tensor([math.pi / 2, 0.0])
    s0 = torch.tensor([[2.0, 1.0, 0.5], [1.0, 1.0, 1.0]])
    c, h, s, r = net.second_box_stage(xyz, fg, feat, oh, c0, h0, s0)
    torch.testing.assert_close((c, h, s), (c0, h0, s0))  # zero output layer: the first box
    assert not r.any()
    with torch.no_grad():
        net.box2_head.out.bias.copy_(torch.tensor([0.1, 0.0, 0.0, 0.2, 0.2, 0.2, 0.05]))
        c, h, s, _ = net.second_box_stage(xyz, fg, feat, oh, c0, h0, s0)
    np.testing.assert_allclose(c.numpy(), [[0.0, 0.2, 3.0], [1.1, 0.5, 2.0]], atol=1e-6)
    np.testing.assert_allclose(s.numpy(), (s0 * math.exp(0.2)).numpy(), rtol=1e-6)
    np.testing.assert_allclose(h.numpy(), (h0 + 0.05).numpy(), atol=1e-6)

    ds = _data(2, neg=1)
    data = TensorData(ds, torch.device("cpu"), 10)
    b = data.batch(torch.arange(data.n), TrainConfig(), augment=False, one_hot_mode="given")
    net = FrustumShapeNet(ModelConfig(**SMALL, box2_widths=(16, 32), box2_fc=(32,)))
    net.eval()  # batch statistics fixed, so the losses of successive steps compare
    out = net(b["points"], b["one_hot"])
    L = compute_losses(out, b, net.mean_sizes, "box")
    keys = ("box2_corner", "box2_center", "box2_size", "box2_heading")
    assert set(keys) <= set(L)
    refine = sum(L[k] for k in keys)
    refine.backward()
    for name, p in net.named_parameters():
        moved = p.grad is not None and bool(p.grad.abs().sum() > 0)
        if not name.startswith(("box2_mlp.", "box2_head.")):
            assert not moved, name
    assert net.box2_head.out.weight.grad.abs().sum() > 0
    params = [p for n, p in net.named_parameters() if n.startswith(("box2_mlp.", "box2_head."))]
    opt = torch.optim.Adam(params, lr=3e-3)
    first = float(refine.detach())
    for _ in range(40):
        out = net(b["points"], b["one_hot"])
        L = compute_losses(out, b, net.mean_sizes, "box")
        loss = sum(L[k] for k in keys)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.7 * first, (first, float(loss.detach()))
    # the box head's own centre is kept apart from the refined one (its losses use it)
    assert "center_head" in out and outputs_differ(out["center_head"], out["center"])


def test_distillation_terms_vanish_on_the_teachers_own_outputs_and_pull_towards_them():
    from shape_detector.model.losses import LossWeights, distillation_losses

    torch.manual_seed(0)
    ds = _data()
    td = TensorData(ds, torch.device("cpu"), 10)
    cfg = TrainConfig.from_dict({})
    b = td.batch(torch.arange(min(8, td.n)), cfg, augment=False, one_hot_mode="train")
    config = ModelConfig.from_dict(dict(SMALL, box2_widths=[16, 32], box2_fc=[16]))
    teacher, student = FrustumShapeNet(config).eval(), FrustumShapeNet(config).eval()
    w = LossWeights.from_dict(dict(distill_seg=1, distill_heading=1, distill_size=1, distill_cls=1, distill_box=1))
    with torch.no_grad():
        t_out = teacher(b["points"], b["one_hot"])
    same = distillation_losses(t_out, t_out, b, w, 2.0)
    assert set(same) == {"distill_seg", "distill_heading", "distill_size", "distill_cls", "distill_box"}
    assert all(float(v) == pytest.approx(0.0, abs=1e-5) for v in same.values())
    # the same box turned by a quarter turn with length and width swapped is the same solid
    turned = dict(t_out, box_heading=t_out["box_heading"] + math.pi / 2, box_size=t_out["box_size"][:, [1, 0, 2]])
    assert float(distillation_losses(turned, t_out, b, w, 2.0)["distill_box"]) == pytest.approx(0.0, abs=1e-5)
    s_out = student(b["points"], b["one_hot"])
    other = distillation_losses(s_out, t_out, b, w, 2.0)
    assert all(float(v.detach()) > 1e-4 for v in other.values())
    assert distillation_losses(s_out, t_out, b, LossWeights(), 2.0) == {}  # off by default
    # one gradient step on the distillation terms alone brings the student closer
    opt = torch.optim.SGD(student.parameters(), lr=0.05)
    sum(other.values()).backward()
    opt.step()
    with torch.no_grad():
        after = distillation_losses(student(b["points"], b["one_hot"]), t_out, b, w, 2.0)
    assert float(sum(after.values())) < float(sum(v.detach() for v in other.values()))
