"""README figure: a grid of generated frames, RGB | depth, with the ground-truth boxes drawn."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..classes import class_color
from ..visualize import colorize_depth, draw_cuboid, save_png
from .generate import SynthConfig, generate_frame


def _annotate(frame, img: np.ndarray, parts: bool = False) -> np.ndarray:
    out = np.ascontiguousarray(img.copy())
    for o in frame.objects:
        col = tuple(int(255 * c) for c in class_color(o.class_name))
        if parts:
            for p in o.parts:
                draw_cuboid(out, p, frame.K, tuple(int(0.5 * c + 0.5 * 255) for c in col), 1)
        draw_cuboid(out, o.cuboid, frame.K, col, 2)
        x1, y1, x2, y2 = (int(round(v)) for v in o.box2d)
        cv2.rectangle(out, (x1, y1), (x2 - 1, y2 - 1), col, 1)
        text = f"{o.class_name} {o.visible_fraction:.2f}"
        org = (x1 + 2, max(12, y1 + 12))
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1, cv2.LINE_AA)
    return out


def make_grid(seed: int = 3, rows: int = 4, cols: int = 2, config: SynthConfig | None = None,
              cell_width: int = 320) -> np.ndarray:
    """``rows x cols`` frames (seeds ``seed*1000 + i``), each shown as RGB | depth with GT 3D boxes."""
    cfg = config or SynthConfig()
    cells = []
    for i in range(rows * cols):
        f = generate_frame(seed * 1000 + i, cfg)
        rgb = _annotate(f, f.rgb)
        dep = _annotate(f, colorize_depth(f.depth, 6.0))
        pair = np.concatenate([rgb, dep], axis=1)
        h = int(round(pair.shape[0] * (2 * cell_width) / pair.shape[1]))
        pair = cv2.resize(pair, (2 * cell_width, h), interpolation=cv2.INTER_AREA)
        pair[:, cell_width - 1: cell_width + 1] = 255
        cells.append(pair)
    h, w = cells[0].shape[:2]
    gap = 6
    grid = np.full((rows * h + (rows - 1) * gap, cols * w + (cols - 1) * gap, 3), 255, np.uint8)
    for i, c in enumerate(cells):
        r, k = divmod(i, cols)
        grid[r * (h + gap): r * (h + gap) + h, k * (w + gap): k * (w + gap) + w] = c
    return grid


def write_figure(out: str | Path, seed: int = 3, rows: int = 4, cols: int = 2) -> Path:
    """Write the :func:`make_grid` figure for ``seed`` to the PNG ``out`` and return its path."""
    grid = make_grid(seed, rows, cols)
    save_png(out, grid)
    return Path(out)
