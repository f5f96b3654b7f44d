"""Walk-through sequences: poses, world ground truth and frames agree."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.synth.generate import SynthConfig
from shape_detector.synth.walkthrough import T_LINK_OPTICAL, camera_poses, link_poses, walkthrough


@pytest.fixture(scope="module")
def wt():
    return walkthrough(1000, 6, config=SynthConfig(width=160, height=120, noise=False, jpeg=False))


def test_shapes_and_stamps(wt):
    assert len(wt.frames) == len(wt.poses) == 6
    assert len(wt.gt_world) >= 4
    stamps = wt.stamps_ns
    assert all(b - a == 200_000_000 for a, b in zip(stamps, stamps[1:]))
    for T in wt.poses:
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert abs(np.linalg.det(R) - 1.0) < 1e-9
        assert np.allclose(T[3], [0, 0, 0, 1])
    for g in wt.gt_world:
        np.testing.assert_allclose(g.rotation[:, 2], [0, 0, 1], atol=1e-9)
        assert g.parts


def test_motion_is_smooth(wt):
    C = np.stack([T[:3, 3] for T in wt.poses])
    assert np.all(np.linalg.norm(np.diff(C, axis=0), axis=1) < 0.5)  # < 2.5 m/s at 5 Hz
    fwd = np.stack([T[:3, 2] for T in wt.poses])
    assert np.all(np.sum(fwd[1:] * fwd[:-1], axis=1) > np.cos(np.radians(40)))


def test_pose_carries_world_gt_onto_its_pixels(wt):
    """Each object's pixels in the instance mask, lifted with the (noise-free) depth and
    moved with the pose, lie inside that object's world box; the camera-frame GT equals the
    moved world GT."""
    from shape_detector.geometry import points_in_box

    checked = 0
    for f, T in zip(wt.frames, wt.poses):
        R, t = T[:3, :3], T[:3, 3]
        np.testing.assert_allclose(f.up, R.T @ [0, 0, 1.0], atol=1e-9)
        for g in f.objects:
            w = wt.gt_world[g.instance_id - 1]
            np.testing.assert_allclose(R @ g.center + t, w.center, atol=1e-6)
            np.testing.assert_allclose(R @ g.rotation, w.rotation, atol=1e-6)
            v, u = np.nonzero((f.instance_mask == g.instance_id) & np.isfinite(f.depth))
            if len(u) < 20:
                continue
            z = f.depth[v, u].astype(np.float64)
            cam = np.stack([(u - f.K[0, 2]) / f.K[0, 0] * z, (v - f.K[1, 2]) / f.K[1, 1] * z, z], axis=1)
            inside = points_in_box(cam @ R.T + t, w.center, w.size, w.rotation, margin=0.02)
            assert inside.mean() > 0.98, f"{w.class_name}: {inside.mean():.2f} of its pixels inside its world box"
            checked += 1
    assert checked >= 3


def test_tf_helpers(wt):
    cams, links = camera_poses(wt), link_poses(wt)
    assert [s for s, _ in cams] == wt.stamps_ns
    for (s, Tc), (s2, Tl) in zip(cams, links):
        assert s == s2
        np.testing.assert_allclose(Tl @ T_LINK_OPTICAL, Tc, atol=1e-12)
        assert Tl[2, 2] > 0.5  # link z roughly up for a hand-held camera


def test_deterministic_and_not_training_streams():
    cfg = SynthConfig(width=64, height=48, noise=False, jpeg=False)
    a, b = walkthrough(1001, 2, config=cfg), walkthrough(1001, 2, config=cfg)
    np.testing.assert_allclose(a.poses[1], b.poses[1])
    assert np.array_equal(a.frames[1].depth, b.frames[1].depth, equal_nan=True)
    with pytest.raises(ValueError):
        walkthrough(1, 0)
