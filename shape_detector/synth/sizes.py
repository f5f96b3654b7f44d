"""Sampled full extents ``(l, w, h)`` of the ten furniture classes (metres; l along the
object's front axis, h up), with means near SUN RGB-D's."""

from __future__ import annotations

import numpy as np


def _n(rng: np.random.Generator, mean: float, sd: float, lo: float, hi: float) -> float:
    return float(np.clip(rng.normal(mean, sd), lo, hi))


def sample_size(name: str, rng: np.random.Generator) -> tuple[float, float, float]:
    """Sample a full extent ``(l, w, h)`` for a class (means near SUN RGB-D's)."""
    if name == "bed":
        l = _n(rng, 2.11, 0.12, 1.85, 2.5)
        w = _n(rng, 1.62, 0.28, 0.9, 2.2)
        h = _n(rng, 1.0, 0.14, 0.72, 1.4) if rng.random() < 0.8 else _n(rng, 0.62, 0.07, 0.45, 0.75)
        return l, w, h
    if name == "table":
        r = rng.random()
        if r < 0.2:  # coffee / side table
            return _n(rng, 0.6, 0.12, 0.4, 0.9), _n(rng, 1.0, 0.25, 0.45, 1.5), _n(rng, 0.46, 0.05, 0.35, 0.6)
        if r < 0.36:  # square / round-ish
            s = _n(rng, 0.85, 0.12, 0.6, 1.2)
            return s, s * rng.uniform(0.97, 1.03), _n(rng, 0.75, 0.03, 0.68, 0.8)
        w = _n(rng, 1.35, 0.3, 0.8, 2.4)
        return min(_n(rng, 0.8, 0.12, 0.55, 1.1), w), w, _n(rng, 0.755, 0.03, 0.68, 0.8)
    if name == "sofa":
        return _n(rng, 0.92, 0.08, 0.72, 1.15), _n(rng, 1.87, 0.35, 0.9, 2.8), _n(rng, 0.85, 0.07, 0.68, 1.05)
    if name == "chair":
        return _n(rng, 0.59, 0.06, 0.42, 0.78), _n(rng, 0.55, 0.06, 0.4, 0.72), _n(rng, 0.83, 0.09, 0.62, 1.15)
    if name == "toilet":
        return _n(rng, 0.70, 0.05, 0.58, 0.82), _n(rng, 0.455, 0.04, 0.36, 0.56), _n(rng, 0.76, 0.05, 0.64, 0.88)
    if name == "desk":
        return _n(rng, 0.70, 0.1, 0.5, 0.95), _n(rng, 1.36, 0.25, 0.8, 2.0), _n(rng, 0.737, 0.03, 0.68, 0.8)
    if name == "dresser":
        return _n(rng, 0.53, 0.06, 0.38, 0.7), _n(rng, 1.0, 0.25, 0.5, 1.7), _n(rng, 1.17, 0.25, 0.7, 1.75)
    if name == "night_stand":
        return _n(rng, 0.50, 0.06, 0.35, 0.65), _n(rng, 0.63, 0.1, 0.4, 0.9), _n(rng, 0.683, 0.08, 0.45, 0.9)
    if name == "bookshelf":
        return _n(rng, 0.405, 0.06, 0.25, 0.6), _n(rng, 1.07, 0.3, 0.45, 1.9), _n(rng, 1.69, 0.35, 0.75, 2.3)
    if name == "bathtub":
        return _n(rng, 0.77, 0.06, 0.62, 0.95), _n(rng, 1.40, 0.18, 1.0, 1.85), _n(rng, 0.473, 0.06, 0.35, 0.65)
    raise ValueError(name)
