"""Materials and procedural textures for the synthetic renderer.

A :class:`Material` is a small record: a texture ``kind`` (plain paint, wood grain, fabric,
floor planks, tiles, carpet, wallpaper stripes, glass, emissive), two colours, a texture scale,
specular strength and an IR reflectivity (how well the depth sensor sees the surface).
Textures are functions of face-local coordinates ``(s, t)`` in metres, evaluated for all
pixels of one kind at once (numpy gathers into cached tileable noise images).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

PLAIN, WOOD, FABRIC, PLANKS, TILES, CARPET, STRIPES, GLASS, EMISSIVE = range(9)
KIND_NAMES = ("plain", "wood", "fabric", "planks", "tiles", "carpet", "stripes", "glass", "emissive")

_NOISE_N = 512


@dataclass
class Material:
    """Surface appearance. Colours are RGB floats in [0, 1] (display space)."""

    kind: int = PLAIN
    color: tuple[float, float, float] = (0.7, 0.7, 0.7)
    color2: tuple[float, float, float] = (0.5, 0.5, 0.5)
    scale: float = 0.1
    spec: float = 0.0
    ir: float = 1.0  # IR reflectivity factor for the depth sensor (low -> dropouts)
    seed: float = 0.0  # texture offset

    def as_row(self) -> np.ndarray:
        """Packed float row: kind, r, g, b, r2, g2, b2, scale, spec, ir, seed."""
        return np.array([self.kind, *self.color, *self.color2, self.scale, self.spec, self.ir, self.seed],
                        dtype=np.float32)


MAT_COLS = 11


@cache
def noise_texture(kind: str = "fractal") -> np.ndarray:
    """Tileable zero-mean, unit-std noise image (512x512 float32), fixed seed (cached).

    ``fractal``: 1/f spectrum (clouds); ``fine``: high-frequency (fabric/carpet);
    ``smooth``: very low frequency (stains, lighting irregularity).
    """
    rng = np.random.default_rng({"fractal": 11, "fine": 12, "smooth": 13}[kind])
    n = _NOISE_N
    f = np.fft.fftfreq(n)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    if kind == "fractal":
        amp = fr ** -1.1
    elif kind == "fine":
        amp = np.exp(-((fr - 0.25) ** 2) / 0.02)
    else:
        amp = fr ** -2.0 * np.exp(-fr / 0.02)
    amp[0, 0] = 0.0
    spec = amp * np.exp(2j * np.pi * rng.random((n, n)))
    img = np.real(np.fft.ifft2(spec))
    img = (img - img.mean()) / (img.std() + 1e-9)
    return img.astype(np.float32)


def sample_noise(img: np.ndarray, s: np.ndarray, t: np.ndarray, scale: float | np.ndarray) -> np.ndarray:
    """Nearest lookup of a tileable noise image at metres ``(s, t)`` * ``scale`` texels/m."""
    n = img.shape[0]
    sc = np.float32(scale) if np.ndim(scale) == 0 else scale
    iu = (s * sc + np.float32(4096.0)).astype(np.int32) & (n - 1)
    iv = (t * sc + np.float32(4096.0)).astype(np.int32) & (n - 1)
    return img.ravel()[(iv << int(np.log2(n))) | iu]


def _hash01(a: np.ndarray, b: np.ndarray | int = 0) -> np.ndarray:
    """Deterministic pseudo-random [0,1) per integer cell (vectorised)."""
    h = (np.asarray(a, dtype=np.int64) * 73856093) ^ (np.asarray(b, dtype=np.int64) * 19349663)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFF).astype(np.float32) / 65536.0


def albedo(kind: int, rows: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-pixel RGB albedo (N,3) for pixels of one texture ``kind``.

    ``rows``: (N, MAT_COLS) material rows per pixel, ``s, t``: (N,) face coords (m).
    """
    c1 = rows[:, 1:4]
    c2 = rows[:, 4:7]
    sc = np.maximum(rows[:, 7], 1e-3)
    off = rows[:, 10]
    s = s + off * np.float32(7.31)
    t = t + off * np.float32(3.17)
    fr = noise_texture("fractal")
    fine = noise_texture("fine")
    sm = noise_texture("smooth")
    if kind == PLAIN or kind == GLASS or kind == EMISSIVE:
        n = sample_noise(sm, s, t, 40.0) * np.float32(0.04)
        n += 1.0
        return c1 * n[:, None]
    if kind == WOOD:
        warp = sample_noise(fr, s, t * 0.15, 60.0) * 0.8
        g = 0.5 + 0.5 * np.sin((t / (sc * 0.05) + warp) * 2 * np.pi)
        g = g ** 3
        fine_n = sample_noise(fine, s * 0.2, t, 400.0) * 0.04
        return (c1 * (1 - g[:, None] * 0.5) + c2 * (g[:, None] * 0.5)) * (1.0 + fine_n)[:, None]
    if kind == FABRIC:
        n = sample_noise(fine, s, t, 500.0) * 0.05 + sample_noise(fr, s, t, 50.0) * 0.05
        weave = 0.03 * np.sin(s * 2 * np.pi / 0.004) * np.sin(t * 2 * np.pi / 0.004)
        return c1 * (1.0 + n + weave)[:, None]
    if kind == CARPET:
        n = sample_noise(fine, s, t, 700.0) * 0.08 + sample_noise(fr, s, t, 20.0) * 0.05
        return c1 * (1.0 + n)[:, None]
    if kind == PLANKS:
        bw = sc  # board width (m) along t
        board = np.floor(t / bw)
        blen = 1.2 + 0.8 * _hash01(board, 7)
        seg = np.floor((s + _hash01(board, 3) * 3.0) / blen)
        h = _hash01(board * 131 + seg, 1)
        base = c1 * (0.85 + 0.3 * h)[:, None] + (c2 - c1) * (0.3 * _hash01(board, seg + 5))[:, None]
        warp = sample_noise(fr, s * 0.1, t, 80.0) * 0.6
        g = (0.5 + 0.5 * np.sin((t / 0.006 + warp + h * 10) * 2 * np.pi)) ** 4
        fb = t / bw - board
        fs = (s + _hash01(board, 3) * 3.0) / blen - seg
        seam = (fb < 0.03) | (fs * blen < 0.004)
        col = base * (1 - 0.15 * g)[:, None]
        col[seam] *= 0.55
        return col
    if kind == TILES:
        ts = sc
        gi, gj = np.floor(s / ts), np.floor(t / ts)
        fu, fv = s / ts - gi, t / ts - gj
        grout = (fu < 0.025) | (fv < 0.025)
        h = _hash01(gi * 977 + gj, 9)
        col = c1 * (0.94 + 0.12 * h)[:, None] * (1.0 + sample_noise(sm, s, t, 30.0) * 0.02)[:, None]
        col[grout] = c2[grout]
        return col
    if kind == STRIPES:
        per = sc
        st = ((s / per) % 1.0) < 0.5
        col = np.where(st[:, None], c1, c2)
        return col * (1.0 + sample_noise(fr, s, t, 200.0) * 0.02)[:, None]
    return c1


# --------------------------------------------------------------------------- palettes

_WOODS = np.array(
    [[0.55, 0.36, 0.2], [0.42, 0.26, 0.14], [0.68, 0.5, 0.32], [0.78, 0.62, 0.42], [0.3, 0.18, 0.1],
     [0.85, 0.72, 0.52], [0.6, 0.42, 0.26], [0.22, 0.13, 0.08]]
)
_PAINTS = np.array(
    [[0.92, 0.92, 0.9], [0.88, 0.86, 0.8], [0.8, 0.82, 0.78], [0.95, 0.93, 0.85], [0.75, 0.8, 0.85],
     [0.85, 0.8, 0.7], [0.7, 0.75, 0.65], [0.9, 0.85, 0.78], [0.82, 0.84, 0.88], [0.96, 0.96, 0.96],
     [0.78, 0.72, 0.62], [0.6, 0.66, 0.72]]
)
_FABRICS = np.array(
    [[0.45, 0.45, 0.48], [0.3, 0.32, 0.4], [0.6, 0.55, 0.45], [0.55, 0.2, 0.18], [0.2, 0.3, 0.25],
     [0.75, 0.72, 0.65], [0.15, 0.15, 0.17], [0.4, 0.3, 0.25], [0.3, 0.4, 0.55], [0.85, 0.82, 0.75],
     [0.5, 0.55, 0.4], [0.62, 0.5, 0.55]]
)


def _jitter(rng: np.random.Generator, c: np.ndarray, amt: float = 0.06) -> tuple[float, float, float]:
    out = np.clip(np.asarray(c) * (1 + rng.normal(0, amt)) + rng.normal(0, amt * 0.5, 3), 0.02, 1.0)
    return (float(out[0]), float(out[1]), float(out[2]))


def wood(rng: np.random.Generator, dark: bool | None = None) -> Material:
    """A wood material (grain), optionally darkened."""
    c = _WOODS[rng.integers(len(_WOODS))]
    if dark:
        c = c * 0.6
    c1 = _jitter(rng, c)
    c2 = tuple(float(v) for v in np.clip(np.array(c1) * rng.uniform(0.55, 0.8), 0, 1))
    return Material(WOOD, c1, c2, float(rng.uniform(0.6, 1.6)), float(rng.uniform(0.0, 0.25)),
                    float(rng.uniform(0.7, 1.0)), float(rng.uniform(0, 100)))


def paint(rng: np.random.Generator, bright: bool = True) -> Material:
    """A flat paint material: a common wall / furniture paint, or a muted random colour when ``bright`` is False."""
    if bright or rng.random() < 0.7:
        c = _PAINTS[rng.integers(len(_PAINTS))]
    else:
        c = _desaturate(rng, rng.uniform(0.1, 0.9, 3))
    c1 = _jitter(rng, c, 0.04)
    return Material(PLAIN, c1, c1, 0.1, float(rng.uniform(0, 0.1)), 1.0, float(rng.uniform(0, 100)))


def _desaturate(rng: np.random.Generator, c: np.ndarray) -> np.ndarray:
    """Real interiors are mostly muted: keep a random, usually small, share of the saturation."""
    m = c.mean()
    return np.clip(m + (c - m) * rng.beta(1.3, 2.6) * 1.3, 0.0, 1.0)


def colored(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.95, spec: float = 0.1) -> Material:
    """A flat material of a muted random colour (channels in ``[lo, hi]``), specular at most ``spec``."""
    c = _desaturate(rng, rng.uniform(lo, hi, 3))
    c1 = tuple(float(v) for v in c)
    return Material(PLAIN, c1, c1, 0.1, float(rng.uniform(0, spec)), float(np.clip(c.mean() * 2.5, 0.15, 1)),
                    float(rng.uniform(0, 100)))


def fabric(rng: np.random.Generator) -> Material:
    """A fabric material (upholstery, bedding)."""
    c1 = _jitter(rng, _FABRICS[rng.integers(len(_FABRICS))], 0.08)
    return Material(FABRIC, c1, c1, 0.1, 0.0, float(np.clip(np.mean(c1) * 2.5, 0.2, 1)), float(rng.uniform(0, 100)))


def leather(rng: np.random.Generator) -> Material:
    """A leather material (dark to light browns, black, off-white), fairly shiny."""
    c = rng.choice([[0.12, 0.08, 0.06], [0.3, 0.16, 0.08], [0.08, 0.08, 0.08], [0.5, 0.35, 0.2], [0.7, 0.68, 0.62]])
    c1 = _jitter(rng, np.array(c))
    return Material(PLAIN, c1, c1, 0.1, float(rng.uniform(0.3, 0.6)), float(np.clip(np.mean(c1) * 2.0, 0.1, 0.9)),
                    float(rng.uniform(0, 100)))


def metal(rng: np.random.Generator) -> Material:
    """A grey metal material, shiny."""
    v = rng.choice([0.1, 0.3, 0.55, 0.75])
    c1 = _jitter(rng, np.array([v, v, v * 1.02]), 0.03)
    return Material(PLAIN, c1, c1, 0.1, float(rng.uniform(0.4, 0.9)), float(rng.uniform(0.2, 0.6)),
                    float(rng.uniform(0, 100)))


def ceramic(rng: np.random.Generator) -> Material:
    """A white ceramic material (sanitary ware), shiny."""
    v = rng.uniform(0.85, 0.97)
    c1 = _jitter(rng, np.array([v, v, v * 0.99]), 0.02)
    return Material(PLAIN, c1, c1, 0.1, float(rng.uniform(0.5, 0.9)), float(rng.uniform(0.5, 0.9)),
                    float(rng.uniform(0, 100)))


def floor(rng: np.random.Generator) -> Material:
    """A floor material: wooden planks, tiles or carpet."""
    r = rng.random()
    if r < 0.4:
        w = wood(rng)
        return Material(PLANKS, w.color, w.color2, float(rng.uniform(0.09, 0.22)), float(rng.uniform(0.05, 0.3)),
                        w.ir, w.seed)
    if r < 0.65:
        c1 = _jitter(rng, _PAINTS[rng.integers(len(_PAINTS))] * rng.uniform(0.6, 1.0))
        c2 = _jitter(rng, np.array(c1) * 0.7)
        return Material(TILES, c1, c2, float(rng.choice([0.3, 0.4, 0.45, 0.6])), float(rng.uniform(0.1, 0.5)), 0.9,
                        float(rng.uniform(0, 100)))
    c1 = _jitter(rng, _FABRICS[rng.integers(len(_FABRICS))] * rng.uniform(0.6, 1.1), 0.08)
    return Material(CARPET, c1, c1, 0.1, 0.0, float(np.clip(np.mean(c1) * 2.2, 0.2, 1)), float(rng.uniform(0, 100)))


def wall(rng: np.random.Generator, bathroom: bool = False) -> Material:
    """A wall material: paint, stripes, or (mostly, in bathrooms) tiles."""
    r = rng.random()
    if bathroom and r < 0.7:
        c1 = _jitter(rng, _PAINTS[rng.integers(len(_PAINTS))])
        c2 = _jitter(rng, np.array(c1) * 0.8)
        return Material(TILES, c1, c2, float(rng.choice([0.1, 0.15, 0.2, 0.3])), 0.3, 0.9, float(rng.uniform(0, 100)))
    if r < 0.1:
        c1 = _jitter(rng, _PAINTS[rng.integers(len(_PAINTS))])
        c2 = _jitter(rng, np.array(c1) * rng.uniform(0.8, 0.95))
        return Material(STRIPES, c1, c2, float(rng.uniform(0.05, 0.3)), 0.0, 1.0, float(rng.uniform(0, 100)))
    return paint(rng)


def glass(rng: np.random.Generator) -> Material:
    """A glass material (returns no depth)."""
    c1 = _jitter(rng, np.array([0.85, 0.9, 0.95]) * rng.uniform(0.7, 1.2), 0.05)
    return Material(GLASS, c1, c1, 0.1, 0.2, 0.0, float(rng.uniform(0, 100)))


def emissive(rng: np.random.Generator, bright: float = 1.0) -> Material:
    """A light-emitting material (lamp shades, screens), ``bright`` scaling its level."""
    v = float(rng.uniform(0.9, 1.0)) * bright
    return Material(EMISSIVE, (v, v, v * 0.97), (v, v, v), 0.1, 0.0, 0.6, 0.0)


def book(rng: np.random.Generator) -> Material:
    """A book spine material: a random, partly desaturated colour."""
    c = rng.uniform(0.05, 0.9, 3)
    c = 0.45 * c + 0.55 * c.mean() * rng.uniform(0.6, 1.1)
    if rng.random() < 0.3:
        c = np.full(3, rng.uniform(0.1, 0.95))
    c1 = tuple(float(v) for v in c)
    return Material(PLAIN, c1, c1, 0.1, float(rng.uniform(0, 0.2)), float(np.clip(c.mean() * 2.5, 0.15, 1)),
                    float(rng.uniform(0, 100)))
