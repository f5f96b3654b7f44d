"""Odometry-like pose errors for the scene evaluation: zero noise is the truth, drift grows
with the distance travelled and keeps gravity, jitter has the asked spread, bad specs refused."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.evaluation.pose_noise import PoseNoise, noisy_poses, parse_pose_noise, travelled

#: camera optical axes in a z-up world: looking along +x
R_WORLD_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def walk(n: int = 41, step: float = 0.1) -> list[np.ndarray]:
    """A camera 1.5 m up walking along +x, ``step`` m per frame."""
    out = []
    for i in range(n):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_WORLD_CAM, [1.0 + step * i, 2.0, 1.5]
        out.append(T)
    return out


def test_zero_noise_gives_the_true_poses():
    poses = walk()
    assert all(np.array_equal(a, b) for a, b in zip(noisy_poses(poses, PoseNoise()), poses))
    np.testing.assert_allclose(travelled(poses)[-1], 4.0)


def test_drift_grows_with_the_distance_and_gravity_stays_right():
    poses = walk()
    noisy = noisy_poses(poses, PoseNoise(drift=0.02, yaw_drift_deg=1.0), seed=3)
    err = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(noisy, poses)]
    assert err[0] == pytest.approx(0.0, abs=1e-12)
    assert all(e2 >= e1 - 1e-12 for e1, e2 in zip(err, err[1:]))  # grows
    # 4 m travelled: 8 cm of translation drift plus 4 degrees of heading about the first position
    assert 0.03 < err[-1] < 0.08 + 4.0 * np.radians(4.0) + 1e-9
    for a, b in zip(noisy, poses):
        up_true, up_noisy = (T[:3, :3].T @ [0.0, 0.0, 1.0] for T in (b, a))
        np.testing.assert_allclose(up_noisy, up_true, atol=1e-9)  # heading drift only
        np.testing.assert_allclose(a[:3, :3].T @ a[:3, :3], np.eye(3), atol=1e-9)
        assert a[2, 3] == pytest.approx(b[2, 3])  # horizontal drift
    heading = np.degrees(np.arctan2(noisy[-1][1, 2], noisy[-1][0, 2]))  # optical axis in the world
    assert abs(heading) == pytest.approx(4.0, abs=1e-6)


def test_jitter_has_the_asked_spread_and_the_seed_repeats_it():
    poses = walk(400, 0.0)  # standing still: jitter only
    noise = PoseNoise(jitter=0.01, jitter_deg=0.5)
    noisy = noisy_poses(poses, noise, seed=1)
    d = np.stack([a[:3, 3] - b[:3, 3] for a, b in zip(noisy, poses)])
    np.testing.assert_allclose(d.std(axis=0), 0.01, rtol=0.15)
    tilt = [np.degrees(np.arccos(np.clip((a[:3, :3].T @ [0, 0, 1]) @ (b[:3, :3].T @ [0, 0, 1]), -1, 1)))
            for a, b in zip(noisy, poses)]
    assert 0.3 < np.median(tilt) < 1.0  # two axes of 0.5 deg tilt gravity
    again = noisy_poses(poses, noise, seed=1)
    assert all(np.array_equal(a, b) for a, b in zip(noisy, again))
    assert not np.array_equal(noisy_poses(poses, noise, seed=2)[5], noisy[5])


def test_specs_are_parsed_and_bad_ones_refused():
    assert parse_pose_noise("0.01, 0.5,0.005,0.2") == PoseNoise(0.01, 0.5, 0.005, 0.2)
    for bad in ("0.01,0.5", "a,b,c,d", "-0.01,0,0,0", "nan,0,0,0"):
        with pytest.raises(ValueError):
            parse_pose_noise(bad)
