"""Box coder: heading / size bin round trips and torch corners vs the numpy geometry."""

from __future__ import annotations

import math

import numpy as np
import torch

from shape_detector.classes import MEAN_SIZES
from shape_detector.geometry import box_corners, rot_z
from shape_detector.model import box_coder as bc




def test_heading_round_trip_torch_and_numpy():
    a = torch.linspace(-3 * math.pi, 3 * math.pi, 997, dtype=torch.float64)
    cls, res = bc.encode_heading(a, 12)
    assert int(cls.min()) >= 0 and int(cls.max()) <= 11
    assert float(res.abs().max()) <= 1.0 + 1e-9
    back = bc.decode_heading(cls, res, 12)
    d = torch.remainder(back - a + math.pi, 2 * math.pi) - math.pi
    assert float(d.abs().max()) < 1e-9
    cls_n, res_n = bc.encode_heading(a.numpy(), 12)
    assert np.array_equal(cls_n, cls.numpy())
    assert np.allclose(bc.decode_heading(cls_n, res_n, 12), back.numpy())
    # bin centres: k * 30 deg has zero residual
    c, r = bc.encode_heading(torch.tensor([0.0, math.pi / 6, -math.pi / 2]), 12)
    assert c.tolist() == [0, 1, 9] and float(r.abs().max()) < 1e-5


def test_size_round_trip():
    rng = np.random.default_rng(0)
    cl = rng.integers(0, 10, 50)
    size = MEAN_SIZES[cl] * rng.uniform(0.5, 1.5, (50, 3))
    res = bc.encode_size(torch.tensor(size), torch.tensor(cl), MEAN_SIZES)
    back = bc.decode_size(torch.tensor(cl), res, MEAN_SIZES)
    assert torch.allclose(back, torch.tensor(size), atol=1e-5)
    assert np.allclose(bc.decode_size(cl, bc.encode_size(size, cl, MEAN_SIZES), MEAN_SIZES), size)


def test_corners_match_geometry():
    c = np.array([0.3, 2.0, -0.4])
    s = np.array([1.2, 0.6, 0.8])
    h = 0.7
    ref = box_corners(c, s, rot_z(h))
    got = bc.box_corners_torch(torch.tensor(c)[None], torch.tensor(s)[None], torch.tensor([h], dtype=torch.float64))[0]
    assert np.allclose(got.numpy(), ref)


def test_split_and_decode_boxes():
    nh, ns = 12, 10
    out = torch.zeros(2, bc.box_head_channels(nh, ns))
    h = bc.split_box_head(out, nh, ns)
    assert h["size_res_norm"].shape == (2, ns, 3)
    h["heading_scores"][:, 3] = 5.0
    h["size_scores"][:, 2] = 5.0
    dec = bc.decode_boxes(torch.zeros(2, 3), h, MEAN_SIZES)
    assert torch.allclose(dec["heading"], torch.full((2,), math.pi / 2))
    assert torch.allclose(dec["size"], torch.tensor(MEAN_SIZES[2]).expand(2, 3))
