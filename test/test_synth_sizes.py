"""Furniture models: per-class size statistics near SUN RGB-D's means, models span their size."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.classes import CLASSES, MEAN_SIZES
from shape_detector.synth import furniture as fu
from shape_detector.synth.sizes import sample_size


@pytest.mark.parametrize("name", CLASSES)
def test_size_statistics(name):
    rng = np.random.default_rng(123)
    sizes = []
    for _ in range(150):
        size = sample_size(name, rng)
        m = fu.build(name, rng, size)
        lo, hi = m.bounds()
        assert np.allclose(hi - lo, size, atol=1e-6), (name, hi - lo, size)  # the model spans its box
        assert np.allclose((lo + hi)[:2], 0, atol=1e-6) and abs(lo[2]) < 1e-9  # centred, on the floor
        sizes.append(hi - lo)
    s = np.array(sizes)
    mean = MEAN_SIZES[CLASSES.index(name)]
    assert np.all(np.abs(s.mean(0) / mean - 1) < 0.1), (name, s.mean(0), mean)
    rel_sd = s.std(0) / s.mean(0)
    assert np.all(rel_sd > 0.03) and np.all(rel_sd < 0.35), (name, rel_sd)


def test_structural_variants():
    rng = np.random.default_rng(0)
    counts = {n: {len(fu.build(n, rng).parts) for _ in range(40)} for n in CLASSES}
    for n, c in counts.items():
        assert len(c) >= 3, (n, c)  # several structurally different models per class


def test_every_class_has_a_builder():
    assert set(fu.BUILDERS) == set(CLASSES)
