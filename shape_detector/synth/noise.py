"""Depth sensor noise model (structured-light / active-stereo RGB-D cameras).

Applied to the clean rendered depth, in this order:

1. **range limits**: nothing nearer than ``min_range`` or beyond ``max_range`` (per frame).
2. **projector shadow**: the IR projector sits ``baseline`` m beside the camera; pixels the
   projector cannot see (behind a nearer surface, seen from the projector) get no depth, giving the
   typical band of missing depth along one side of foreground objects.
3. **grazing / dark / glass dropout**: missing with a probability rising as the surface turns edge-on
   (``|n . ray|`` small), as its IR reflectivity x albedo falls (dark, shiny) and with distance; glass
   returns nothing.
4. **depth edges**: pixels next to a depth discontinuity are dropped or turned into "flying pixels"
   (a mix of foreground and background depth).
5. **random holes**: a smooth random field thresholded into blobs; optionally an invalid band along
   the image border (depth-to-colour registration).
6. **axial noise**: Gaussian with ``sigma(z) = scale * (0.0012 + 0.0019 (z - 0.4)^2)`` m (Nguyen et al.
   2012, Kinect), partly spatially correlated (unit variance overall).
7. **quantisation** to 1 mm. Invalid pixels are NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class NoiseParams:
    """Per-frame depth sensor settings (ranges and baseline in metres; the steps are described in the module
    docstring)."""

    sigma_scale: float = 1.0
    min_range: float = 0.45
    max_range: float = 6.0
    baseline: float = 0.075
    shadow_side: int = 1  # +1: shadows on the right of foreground objects, -1 left
    grazing_cos: float = 0.2
    dark_level: float = 0.1
    edge_drop: float = 0.5
    flying: float = 0.25
    hole_fraction: float = 0.01
    correlated: float = 0.6  # share of the noise variance that is spatially correlated
    quant_m: float = 0.001
    border: tuple[int, int, int, int] = (0, 0, 0, 0)  # invalid band (left, right, top, bottom) px, registration

    @classmethod
    def sample(cls, rng: np.random.Generator) -> NoiseParams:
        """Random settings spanning typical structured-light / active-stereo sensors."""
        return cls(
            sigma_scale=float(rng.uniform(0.8, 1.6)),
            min_range=float(rng.uniform(0.35, 0.55)),
            max_range=float(rng.uniform(5.5, 10.0)),
            baseline=float(rng.uniform(0.05, 0.075)),
            shadow_side=1 if rng.random() < 0.8 else -1,
            grazing_cos=float(rng.uniform(0.12, 0.3)),
            dark_level=float(rng.uniform(0.06, 0.16)),
            edge_drop=float(rng.uniform(0.3, 0.8)),
            flying=float(rng.uniform(0.1, 0.4)),
            hole_fraction=float(rng.uniform(0.0, 0.02)) if rng.random() < 0.6 else 0.0,
            correlated=float(rng.uniform(0.3, 0.8)),
            border=tuple(int(v) for v in (rng.integers(0, 17, 4) * np.array([1, 0.5, 0.3, 0.3]) * (rng.random() < 0.5))),
        )


def randn(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Fast float32 standard normal field (OpenCV's RNG, seeded from ``rng``: deterministic)."""
    out = np.empty((int(np.prod(shape[:-1])) if len(shape) > 1 else 1, shape[-1]), np.float32)
    cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
    cv2.randn(out, 0.0, 1.0)
    return out.reshape(shape)


def randu(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Fast float32 uniform [0, 1) field (OpenCV's RNG, seeded from ``rng``)."""
    out = np.empty((int(np.prod(shape[:-1])) if len(shape) > 1 else 1, shape[-1]), np.float32)
    cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
    cv2.randu(out, 0.0, 1.0)
    return out.reshape(shape)


def axial_sigma(z: np.ndarray | float, scale: float = 1.0) -> np.ndarray:
    """Standard deviation (m) of the axial depth noise at depth ``z`` (m)."""
    z = np.asarray(z, dtype=np.float64)
    return scale * (0.0012 + 0.0019 * (z - 0.4) ** 2)


_BLUR = 2.0


def _corr_norm() -> float:
    """std of a Gaussian-blurred unit white-noise field (for renormalising), measured once."""
    w = np.random.default_rng(0).standard_normal((512, 512)).astype(np.float32)
    return float(cv2.GaussianBlur(w, (0, 0), _BLUR)[32:-32, 32:-32].std())


_CORR_STD = _corr_norm()


def shadow_mask(z: np.ndarray, fx: float, baseline: float, side: int = 1) -> np.ndarray:
    """Pixels hidden from a projector ``baseline`` m to the side of the camera (``side``=+1: on its left)."""
    H, W = z.shape
    zz = np.where(np.isfinite(z) & (z > 0), z, np.float32(1e6)).astype(np.float32, copy=False)
    u = np.arange(W, dtype=np.float32)[None, :]
    if side < 0:
        zz = zz[:, ::-1]
    up = u + np.float32(fx * baseline) / zz  # projector column of each pixel
    prev = np.maximum.accumulate(up, axis=1)
    prev = np.concatenate([np.full((H, 1), -np.inf), prev[:, :-1]], axis=1)
    sh = prev > up + np.float32(0.5)
    return sh[:, ::-1] if side < 0 else sh


def apply_depth_noise(depth: np.ndarray, K: np.ndarray, rng: np.random.Generator, params: NoiseParams,
                      cos_incidence: np.ndarray | None = None, reflectivity: np.ndarray | None = None,
                      glass: np.ndarray | None = None) -> np.ndarray:
    """Noisy float32 depth (NaN invalid) from clean ``depth`` (inf = no surface).

    ``cos_incidence``: |n . unit ray| per pixel; ``reflectivity``: IR reflectivity x albedo in [0,1];
    ``glass``: boolean mask of transparent surfaces.
    """
    H, W = depth.shape
    z = depth.astype(np.float32)
    valid = np.isfinite(z) & (z >= params.min_range) & (z <= params.max_range)
    valid &= ~shadow_mask(z, K[0, 0], params.baseline, params.shadow_side)
    bl, br, bt, bb = (int(round(b * W / 640.0)) for b in params.border)
    if bl:
        valid[:, :bl] = False
    if br:
        valid[:, W - br:] = False
    if bt:
        valid[:bt] = False
    if bb:
        valid[H - bb:] = False
    drop_p = np.zeros((H, W), np.float32)
    if cos_incidence is not None:
        c = cos_incidence.astype(np.float32, copy=False)
        drop_p += np.sqrt(np.clip((params.grazing_cos - c) * np.float32(1.0 / params.grazing_cos), 0, 1))
    if reflectivity is not None:
        zf = np.where(np.isfinite(depth), depth, 10.0).astype(np.float32)
        thr = np.float32(params.dark_level) * (0.5 + 0.5 * (zf * np.float32(1 / 3.0)) ** 2)
        drop_p += np.sqrt(np.clip((thr - reflectivity.astype(np.float32)) / np.maximum(thr, 1e-6), 0, 1))
    if glass is not None:
        valid &= ~glass
    # depth edges
    zf = np.where(np.isfinite(z), z, np.float32(50.0))
    zmax = cv2.dilate(zf, np.ones((3, 3), np.uint8))
    zmin = cv2.erode(zf, np.ones((3, 3), np.uint8))
    edge = (zmax - zmin) > 0.04 * zmin + 0.02
    drop_p[edge] += params.edge_drop
    # random holes: a few irregular blobs
    if params.hole_fraction > 0:
        g = rng.standard_normal((H // 40 + 3, W // 40 + 3)).astype(np.float32)
        g = cv2.resize(g, (W + 80, H + 80), interpolation=cv2.INTER_CUBIC)[40:40 + H, 40:40 + W]
        g += 0.25 * cv2.resize(rng.standard_normal((H // 8 + 1, W // 8 + 1)).astype(np.float32), (W, H),
                               interpolation=cv2.INTER_LINEAR)
        thr = np.quantile(g[::4, ::4], 1.0 - params.hole_fraction)
        valid &= ~(g > thr)
    # dropout: compare with a partly smooth random field, so missing depth comes in patches
    sm = cv2.resize(rng.standard_normal((H // 6 + 1, W // 6 + 1)).astype(np.float32), (W, H),
                    interpolation=cv2.INTER_LINEAR)
    x = np.float32(0.8 / 0.75) * sm + np.float32(0.6) * randn(rng, (H, W))
    # drop where sigmoid(1.702 x) < p  <=>  x < logit(p) / 1.702 (x is ~ standard normal)
    pos = np.flatnonzero(drop_p > 0)
    if len(pos):
        p = np.minimum(drop_p.ravel()[pos], np.float32(1 - 1e-6))
        lim = np.log(p / (1 - p)) * np.float32(1 / 1.702)
        vf = valid.ravel()
        vf[pos] &= x.ravel()[pos] >= lim
    # flying pixels: some surviving edge pixels take a mix of nearby fore/background depth
    fly = edge & valid & (randu(rng, (H, W)) < params.flying)
    if np.any(fly):
        a = rng.random(int(fly.sum()))
        z[fly] = np.minimum(zmin[fly], 20) * (1 - a) + np.minimum(zmax[fly], 20) * a
    # axial noise, partly spatially correlated, unit variance overall
    white = randn(rng, (H, W))
    corr = cv2.GaussianBlur(randn(rng, (H, W)), (0, 0), _BLUR) / _CORR_STD
    cw = np.sqrt(params.correlated)
    n = np.sqrt(1 - params.correlated) * white + cw * corr
    zn = np.where(valid, z, np.float32(0.0))
    d = zn - np.float32(0.4)
    zn += (np.float32(params.sigma_scale * 0.0012) + np.float32(params.sigma_scale * 0.0019) * d * d) * n
    if params.quant_m > 0:
        zn = np.round(zn * np.float32(1.0 / params.quant_m)) * np.float32(params.quant_m)
    out = zn.astype(np.float32, copy=False)
    out[~valid] = np.nan
    return out
