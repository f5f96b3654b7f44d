"""Cuboid primitives: distances, surface sampling, coverage / consistency, Monte-Carlo IoU."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from shape_detector.model import primitives as pr




def _cub(center, size, rot=None):
    c = torch.tensor(center, dtype=torch.float64).view(1, 1, 3)
    s = torch.tensor(size, dtype=torch.float64).view(1, 1, 3)
    R = torch.eye(3, dtype=torch.float64).view(1, 1, 3, 3) if rot is None else torch.as_tensor(rot).view(1, 1, 3, 3)
    return c, s, R


def test_point_cuboid_distance_hand_cases():
    c, s, R = _cub([0, 0, 0], [2, 2, 2])
    pts = torch.tensor(
        [[0, 0, 0], [0.5, -0.9, 0.2], [1, 0, 0], [3, 0, 0], [2, 2, 0], [2, 3, 4], [-1.5, 0.2, 0.0]],
        dtype=torch.float64,
    ).view(1, -1, 3)
    d2 = pr.point_cuboid_sqdist(pts, c, s, R)[0, :, 0]
    expect = [0, 0, 0, 4, 2, 1 + 4 + 9, 0.25]  # inside, inside, on face, face, edge, corner, face
    assert torch.allclose(d2, torch.tensor(expect, dtype=torch.float64))


def test_point_cuboid_distance_rotated_and_translated():
    th = 0.6
    Rz = torch.tensor([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]], dtype=torch.float64)
    c, s, R = _cub([1, 2, 3], [2, 1, 1], Rz)
    # a point 0.5 beyond the +x face along the rotated x axis
    p = (torch.tensor([1, 2, 3], dtype=torch.float64) + Rz[:, 0] * 1.5).view(1, 1, 3)
    assert abs(float(pr.point_cuboid_sqdist(p, c, s, R)) - 0.25) < 1e-12


def test_quaternion_rotations_are_orthonormal():
    q = torch.randn(50, 4, dtype=torch.float64)
    R = pr.quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(50, 3, 3)
    assert torch.allclose(R @ R.transpose(1, 2), eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=torch.float64))
    assert torch.allclose(pr.quat_to_rotmat(torch.tensor([[2.0, 0, 0, 0]])), torch.eye(3)[None])


def test_surface_samples_lie_on_faces_and_are_differentiable():
    size = torch.tensor([[[1.0, 2.0, 0.5]]], requires_grad=True)
    c = torch.tensor([[[0.2, 0.0, -0.1]]])
    R = torch.eye(3).view(1, 1, 3, 3)
    pts, w = pr.sample_cuboid_surface(c, size, R, 30)
    assert pts.shape == (1, 1, 180, 3) and torch.allclose(w.sum(-1), torch.ones(1, 1))
    local = (pts - c.unsqueeze(2)).abs()
    on_face = ((local - 0.5 * size.unsqueeze(2)).abs() < 1e-6).any(-1)
    assert bool(on_face.all())
    assert bool((local <= 0.5 * size.unsqueeze(2) + 1e-6).all())
    # area weighting: the two largest faces (1 x 2) get the largest weight
    assert float(w[0, 0, 120]) > float(w[0, 0, 0])
    pts.sum().backward()
    assert size.grad is not None and torch.isfinite(size.grad).all()


def _parts():
    # a table: top + 4 legs (canonical frame)
    cen = [[0, 0, 0.35], [0.35, 0.55, -0.05], [-0.35, 0.55, -0.05], [0.35, -0.55, -0.05], [-0.35, -0.55, -0.05]]
    siz = [[0.8, 1.2, 0.05], [0.05, 0.05, 0.75], [0.05, 0.05, 0.75], [0.05, 0.05, 0.75], [0.05, 0.05, 0.75]]
    rot = [np.eye(3)] * 5
    return np.array(cen), np.array(siz), np.array(rot)


def test_coverage_zero_for_gt_parts_and_positive_otherwise():
    cen, siz, rot = _parts()
    rng = np.random.default_rng(0)
    surf = pr.sample_parts_surface_np(cen, siz, rot, 256, rng)
    assert surf.shape == (256, 3)
    prims = {
        "center": torch.tensor(cen)[None],
        "size": torch.tensor(siz)[None],
        "rotation": torch.tensor(rot)[None],
    }
    X = torch.tensor(surf)[None]
    assert float(pr.coverage_loss(X, prims, 1)) < 1e-10
    # with l = 3 the 2nd/3rd nearest primitives count too -> positive
    assert float(pr.coverage_loss(X, prims, 3)) > 0
    # drop the legs: the leg samples are uncovered
    top = {k: v[:, :1] for k, v in prims.items()}
    assert float(pr.coverage_loss(X, top, 1)) > 1e-4


def test_parts_surface_samples_not_inside_other_parts():
    cen = np.array([[0, 0, 0], [0.5, 0, 0]])
    siz = np.array([[1.0, 1, 1], [1.0, 1, 1]])
    rot = np.stack([np.eye(3)] * 2)
    pts = pr.sample_parts_surface_np(cen, siz, rot, 500, np.random.default_rng(1))
    # union is x in [-0.5, 1]; nothing strictly inside
    assert np.all(pts[:, 0] >= -0.5 - 1e-9) and np.all(pts[:, 0] <= 1 + 1e-9)
    inner = (np.abs(pts[:, 1]) < 0.5 - 1e-6) & (np.abs(pts[:, 2]) < 0.5 - 1e-6) & (pts[:, 0] > -0.5 + 1e-6) & (pts[:, 0] < 1 - 1e-6)
    assert not inner.any()


def test_consistency_zero_inside_gt_and_positive_outside():
    cen, siz, rot = _parts()
    pc, ps, prot = (torch.tensor(a)[None] for a in (cen, siz, rot))
    mask = torch.ones(1, 5, dtype=torch.bool)
    inside = {  # two primitives strictly inside the table top / a leg
        "center": torch.tensor([[[0.1, 0.1, 0.35], [0.35, 0.55, -0.1]]], dtype=torch.float64),
        "size": torch.tensor([[[0.3, 0.3, 0.02], [0.02, 0.02, 0.3]]], dtype=torch.float64),
        "rotation": torch.eye(3, dtype=torch.float64).expand(1, 2, 3, 3),
    }
    assert float(pr.consistency_loss(inside, pc, ps, prot, mask)) < 1e-12
    outside = dict(inside)
    outside["center"] = inside["center"] + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    assert float(pr.consistency_loss(outside, pc, ps, prot, mask)) > 1e-3
    # padded parts are ignored
    mask2 = mask.clone()
    mask2[0, 0] = False
    assert float(pr.consistency_loss(inside, pc, ps, prot, mask2)) > 1e-4


def test_primitive_params_within_box_and_mc_iou():
    raw = torch.randn(4, 6, 10) * 3
    box = torch.tensor([[1.0, 2.0, 0.8]]).expand(4, 3)
    p = pr.primitive_params(raw, box)  # sizes softly capped at 1.25 box, no saturation
    assert bool((p["size"] <= 1.26 * box.unsqueeze(1)).all()) and bool((p["size"] > 0).all())
    raw.requires_grad_(True)
    q = pr.primitive_params(raw, box)
    (q["size"].sum() + q["center"].sum()).backward()
    assert bool((raw.grad[..., 7:10].abs() > 0.1).all())  # translation gradient never vanishes
    cen, siz, rot = _parts()
    pc, ps, prot = (torch.tensor(a, dtype=torch.float32)[None] for a in (cen, siz, rot))
    same = {"center": pc, "size": ps, "rotation": prot}
    assert float(pr.shape_iou_mc(same, pc, ps, prot, num_samples=4000)) > 0.999
    half = {"center": pc[:, :1] + torch.tensor([0.4, 0, 0]), "size": ps[:, :1], "rotation": prot[:, :1]}
    iou = float(pr.shape_iou_mc(half, pc[:, :1], ps[:, :1], prot[:, :1], num_samples=20000, generator=torch.Generator().manual_seed(0)))
    assert abs(iou - 1 / 3) < 0.03


def test_matched_part_loss_zero_for_permuted_parts_and_finds_assignment():
    cen, siz, rot = _parts()
    pc, ps, prot = (torch.tensor(a, dtype=torch.float64)[None] for a in (cen, siz, rot))
    mask = torch.ones(1, 5, dtype=torch.bool)
    perm = torch.tensor([3, 0, 4, 1, 2])
    # 6 primitives: the 5 parts (permuted) + a small extra one inside the top
    prims = {
        "center": torch.cat([pc[:, perm], torch.tensor([[[0.0, 0.0, 0.35]]], dtype=torch.float64)], 1),
        "size": torch.cat([ps[:, perm], torch.tensor([[[0.1, 0.1, 0.02]]], dtype=torch.float64)], 1),
        "rotation": torch.cat([prot[:, perm], torch.eye(3, dtype=torch.float64).view(1, 1, 3, 3)], 1),
    }
    tc, ts, tr, tm = pr.largest_parts(pc, ps, prot, mask, 6)
    assert tm.tolist() == [[True] * 5 + [False]]
    assign = pr.match_primitives(prims, tc, ts, tr, tm)
    for k in range(5):  # target k is matched to the primitive holding the same part
        assert torch.allclose(prims["center"][0, assign[0, k]], tc[0, k])
    assert float(pr.matched_part_loss(prims, pc, ps, prot, mask)) < 1e-12
    moved = dict(prims)
    moved["center"] = prims["center"] + torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)
    assert float(pr.matched_part_loss(moved, pc, ps, prot, mask)) > 1e-4
    # a 90-degree-rotated primitive with swapped sizes is the same cuboid: still zero
    rz = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    sw = {k: v.clone() for k, v in prims.items()}
    j = int(assign[0, 0])
    sw["rotation"][0, j] = rz
    sw["size"][0, j] = prims["size"][0, j][[1, 0, 2]]
    assert float(pr.matched_part_loss(sw, pc, ps, prot, mask)) < 1e-12


def test_volume_consistency_zero_inside_and_penalises_empty_space():
    cen, siz, rot = _parts()
    pc, ps, prot = (torch.tensor(a, dtype=torch.float64)[None] for a in (cen, siz, rot))
    mask = torch.ones(1, 5, dtype=torch.bool)
    same = {"center": pc, "size": ps, "rotation": prot}
    assert float(pr.volume_consistency_loss(same, pc, ps, prot, mask)) < 1e-12
    # a blob between the legs (under the top): its surface touches the legs, its inside is empty
    blob = {"center": torch.tensor([[[0.0, 0.0, -0.05]]], dtype=torch.float64),
            "size": torch.tensor([[[0.7, 1.1, 0.7]]], dtype=torch.float64),
            "rotation": torch.eye(3, dtype=torch.float64).view(1, 1, 3, 3)}
    v = float(pr.volume_consistency_loss(blob, pc, ps, prot, mask, per_primitive=2000))
    assert v > 0.01


def test_occupancy_iou_loss_matches_the_volume_iou_and_shrinks_air_blocks():
    cen, siz, rot = _parts()  # a table: top and four legs, z from -0.425 to 0.375
    pc, ps, prot = (torch.tensor(a, dtype=torch.float64)[None] for a in (cen, siz, rot))
    mask = torch.ones(1, 5, dtype=torch.bool)
    box = torch.tensor([[0.8, 1.2, 0.85]], dtype=torch.float64)  # sampling window (x1.3) holds every part
    g = torch.Generator().manual_seed(0)
    same = {"center": pc, "size": ps, "rotation": prot}
    assert float(pr.occupancy_iou_loss(same, pc, ps, prot, mask, box, 20000, temperature=1e-4, generator=g)) < 0.02
    # the parts' bounding box as one primitive: IoU = parts volume / its volume (hand-computed)
    whole = {"center": torch.tensor([[[0.0, 0.0, -0.025]]], dtype=torch.float64),
             "size": torch.tensor([[[0.8, 1.2, 0.8]]], dtype=torch.float64),
             "rotation": torch.eye(3, dtype=torch.float64).view(1, 1, 3, 3)}
    vol = float(np.prod(siz, 1).sum())  # the parts do not overlap
    want = 1.0 - vol / (0.8 * 1.2 * 0.8)
    got = float(pr.occupancy_iou_loss(whole, pc, ps, prot, mask, box, 50000, temperature=1e-4, generator=g))
    assert got == pytest.approx(want, abs=0.01)
    # a primitive reaching out of the box pays for the outside air too
    big = dict(whole, size=whole["size"] * 1.2)
    assert float(pr.occupancy_iou_loss(big, pc, ps, prot, mask, box, 50000, temperature=1e-4, generator=g)) > got + 0.01
    # with the exact top, a block of air between the legs lowers the IoU; its gradient shrinks it
    size = torch.tensor([[0.5, 0.9, 0.5]], dtype=torch.float64, requires_grad=True)
    two = {"center": torch.tensor([[[0.0, 0.0, 0.35], [0.0, 0.0, -0.05]]], dtype=torch.float64),
           "size": torch.cat([ps[:, :1], size.view(1, 1, 3)], 1),
           "rotation": torch.eye(3, dtype=torch.float64).expand(1, 2, 3, 3)}
    top = {k: v[:, :1] for k, v in two.items()}
    with_air = pr.occupancy_iou_loss(two, pc, ps, prot, mask, box, 20000, generator=g)
    without = pr.occupancy_iou_loss(top, pc, ps, prot, mask, box, 20000, generator=g)
    assert float(with_air.detach()) > float(without.detach()) + 0.2
    with_air.sum().backward()
    assert bool((size.grad > 0).all())
