"""Depth noise model statistics."""

from __future__ import annotations

import numpy as np

from shape_detector.synth.noise import NoiseParams, apply_depth_noise, axial_sigma, shadow_mask

K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])


def _plain(**kw) -> NoiseParams:
    base = dict(hole_fraction=0.0, edge_drop=0.0, flying=0.0, max_range=8.0, min_range=0.4)
    base.update(kw)
    return NoiseParams(**base)


def test_axial_noise_matches_model():
    rng = np.random.default_rng(0)
    for z in (1.0, 2.0, 3.5, 5.0):
        for scale in (1.0, 1.5):
            depth = np.full((240, 320), z, np.float32)
            out = apply_depth_noise(depth, K, rng, _plain(sigma_scale=scale))
            err = out[np.isfinite(out)] - z
            assert np.isfinite(out).mean() > 0.99
            sd = axial_sigma(z, scale)
            assert abs(err.std() / sd - 1) < 0.12, (z, scale, err.std(), sd)
            assert abs(err.mean()) < 0.2 * sd + 0.0005


def test_quantisation_and_range():
    rng = np.random.default_rng(1)
    depth = np.tile(np.linspace(0.2, 9.0, 320, dtype=np.float32), (60, 1))
    out = apply_depth_noise(depth, K, rng, _plain(max_range=6.0, min_range=0.5))
    v = out[np.isfinite(out)]
    assert np.allclose(v * 1000, np.round(v * 1000), atol=1e-3)  # 1 mm steps
    assert np.all(np.isnan(out[depth > 6.05])) and np.all(np.isnan(out[depth < 0.49]))


def test_projector_shadow_width():
    z = np.full((10, 200), 3.0)
    z[:, 50:100] = 1.0
    fb = 525.0 * 0.075
    sh = shadow_mask(z, 525.0, 0.075, side=1)
    width = fb * (1 / 1.0 - 1 / 3.0)
    cols = np.nonzero(sh[0])[0]
    assert cols.min() == 100 and abs(len(cols) - width) <= 1.5


def test_dark_grazing_glass_dropout():
    rng = np.random.default_rng(2)
    depth = np.full((120, 160), 2.5, np.float32)
    p = _plain(dark_level=0.1, grazing_cos=0.2)
    bright = apply_depth_noise(depth, K, rng, p, np.ones_like(depth), np.ones_like(depth))
    dark = apply_depth_noise(depth, K, rng, p, np.ones_like(depth), np.full_like(depth, 0.01))
    grazing = apply_depth_noise(depth, K, rng, p, np.full_like(depth, 0.05), np.ones_like(depth))
    glass = apply_depth_noise(depth, K, rng, p, glass=np.ones(depth.shape, bool))
    assert np.isfinite(bright).mean() > 0.99
    assert np.isfinite(dark).mean() < 0.4
    assert np.isfinite(grazing).mean() < 0.6
    assert np.isfinite(glass).mean() == 0


def test_edges_and_holes():
    rng = np.random.default_rng(3)
    depth = np.full((240, 320), 3.0, np.float32)
    depth[:, 160:] = 1.5
    out = apply_depth_noise(depth, K, rng, _plain(edge_drop=1.0, hole_fraction=0.03))
    assert np.isnan(out[:, 159:161]).mean() > 0.9 and np.isnan(out[:, 150:155]).mean() < 0.1
    assert 0.01 < np.isnan(out).mean() < 0.1
