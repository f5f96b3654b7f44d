"""Learned 2D proposals: a small CenterNet-style network on the RGB-D frame.

The frame is resized to :data:`INPUT_SIZE` (colour, depth and a valid-depth mask, five
channels, :func:`prepare_input`). The network gives a heatmap of object centres and, per
cell of the output grid (every :data:`STRIDE` input pixels), the sub-cell offset and the log
width and height of the box (:func:`decode`). It is class-agnostic: the proposal
classifier names the class, as for the geometric proposals. The network is trained on the
generator's frames (``shape-detector train-proposer``, :mod:`shape_detector.training.train_proposer`)
and shipped as an ONNX file, run with ONNX Runtime where installed, else OpenCV DNN, so
neither needs torch. Beside it lies its int8 version (:mod:`.learned_int8`), which ONNX
Runtime runs under ``precision`` ``auto`` and ``int8`` (:func:`model_file`).

Boxes are ``(x1, y1, x2, y2)`` pixel edges of the full-size image.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np

from . import Proposal

#: network input (width, height) in pixels
INPUT_SIZE = (160, 120)
#: input pixels per output cell
STRIDE = 4
#: depth (m) mapped to 0 by the input normalisation (d / DEPTH_SCALE - 1)
DEPTH_SCALE = 4.0
#: the shipped network
DEFAULT_MODEL = Path(__file__).resolve().parent.parent / "weights" / "proposer2d.onnx"


def prepare_input(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(5, H, W) float32 network input at :data:`INPUT_SIZE`: colour in [-0.5, 0.5], depth
    (metres; 0 / NaN invalid) as ``d / 4 - 1`` (0 where invalid) and the valid mask."""
    w, h = INPUT_SIZE
    c = cv2.resize(np.asarray(rgb), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0 - 0.5
    # nearest-neighbour sampling copies values, so invalid ones can be zeroed after it, on 1/16 of the pixels
    d = np.nan_to_num(cv2.resize(np.asarray(depth, dtype=np.float32), (w, h), interpolation=cv2.INTER_NEAREST))
    valid = (d > 0.05).astype(np.float32)
    dn = np.where(valid > 0, d / DEPTH_SCALE - 1.0, 0.0).astype(np.float32)
    return np.concatenate([c.transpose(2, 0, 1), dn[None], valid[None]], axis=0)


def decode(heatmap: np.ndarray, reg: np.ndarray, width: int, height: int, k: int = 20,
           min_score: float = 0.05) -> list[tuple[float, float, float, float, float]]:
    """Boxes ``(x1, y1, x2, y2, score)`` (pixels of a ``width`` x ``height`` image, clipped
    to it, best first) from one frame's outputs: ``heatmap`` (h, w) logits, ``reg`` (4, h, w)
    = offset x, offset y, log width, log height in output cells. A cell is a centre when it
    is the maximum of its 3x3 neighbourhood and scores at least ``min_score``."""
    # logits below -700 would overflow exp(); clipped, they still map to probability ~0
    p = 1.0 / (1.0 + np.exp(-np.clip(np.asarray(heatmap, dtype=np.float64), -700.0, 700.0)))
    hh, ww = p.shape
    win = cv2.dilate(p, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=-1.0)
    peaks = np.flatnonzero((p >= win) & (p >= min_score))
    order = peaks[np.argsort(-p.ravel()[peaks], kind="stable")][:k]
    iy, ix = np.divmod(order, ww)
    cx, cy = ix + reg[0, iy, ix], iy + reg[1, iy, ix]
    bw, bh = np.exp(np.clip(reg[2, iy, ix], -5, 6)), np.exp(np.clip(reg[3, iy, ix], -5, 6))
    fx, fy = width / ww, height / hh
    x1 = np.clip((cx - bw / 2) * fx, 0, width)
    x2 = np.clip((cx + bw / 2) * fx, 0, width)
    y1 = np.clip((cy - bh / 2) * fy, 0, height)
    y2 = np.clip((cy + bh / 2) * fy, 0, height)
    s = p.ravel()[order]
    return [(float(a), float(b), float(c), float(d), float(e)) for a, b, c, d, e in zip(x1, y1, x2, y2, s)
            if c - a >= 1.0 and d - b >= 1.0]


def model_file(path: Path, precision: str = "auto") -> Path:
    """The file to run for the network ``path``: under ``precision`` ``int8``, its int8 version
    (:func:`~.learned_int8.int8_path`) where that exists, was built from this very file and ONNX
    Runtime is installed; else ``path`` (``auto`` included: the int8 boxes cost the detector
    accuracy, see the model card)."""
    from ..model.onnx_backend import ort_available
    from .learned_int8 import int8_path, int8_source_matches

    q = int8_path(path)
    if precision == "int8" and q.is_file() and ort_available():
        if int8_source_matches(q, path):
            return q
        warnings.warn(f"{q.name} was not built from {path.name} (its provenance names another file): running "
                      "the float32 network; rebuild it with shape-detector train-proposer --int8-only", stacklevel=3)
    return path


class _Runner:
    """The ONNX graph (``input`` (B,5,H,W) -> ``heatmap`` (B,1,h,w), ``reg`` (B,4,h,w)) in
    ONNX Runtime, else OpenCV DNN."""

    def __init__(self, path: Path, num_threads: int = 1) -> None:
        from ..model.onnx_backend import make_session, ort_available

        self.session = make_session(path, num_threads) if ort_available() else None
        if self.session is None:
            self.net = cv2.dnn.readNetFromONNX(str(path))

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.session is not None:
            hm, reg = self.session.run(["heatmap", "reg"], {"input": x})
            return hm, reg
        self.net.setInput(x)
        hm, reg = self.net.forward(["heatmap", "reg"])
        return hm, reg


class LearnedProposer:
    """Class-agnostic proposals from the learned network (``model_path``: an ONNX file from
    ``shape-detector train-proposer``; default the shipped one); ``max_proposals`` best
    centres scoring at least ``min_score``; ``precision``: ``int8`` runs the int8 version
    where there is one (:func:`model_file`), ``auto`` and ``fp32`` the file itself.

    Scores are mapped onto ``score_range``: the proposal classifier, which takes a
    proposal's score as one of its inputs, was trained on the geometric proposer's, which
    lie in that range.
    """

    def __init__(self, model_path: str | Path | None = None, max_proposals: int = 20, min_score: float = 0.05,
                 score_range: tuple[float, float] = (0.75, 1.0), num_threads: int = 1,
                 precision: str = "auto") -> None:
        path = Path(model_path) if model_path else DEFAULT_MODEL
        if not path.is_file():
            raise FileNotFoundError(f"no learned proposer model at {path} (shape-detector train-proposer writes one)")
        path = model_file(path, precision)
        self.path = path
        self.max_proposals = int(max_proposals)
        self.min_score = float(min_score)
        self.score_range = (float(score_range[0]), float(score_range[1]))
        self._run = _Runner(path, num_threads)

    def detect(self, rgb: np.ndarray, depth: np.ndarray) -> list[Proposal]:
        """The frame's proposals, best first (colour uint8 RGB, depth metres, same size)."""
        h, w = np.shape(depth)[:2]
        hm, reg = self._run(prepare_input(rgb, depth)[None])
        lo, hi = self.score_range
        return [Proposal((x1, y1, x2, y2), None, lo + (hi - lo) * s, "learned")
                for x1, y1, x2, y2, s in decode(hm[0, 0], reg[0], w, h, self.max_proposals, self.min_score)]

    def __call__(self, depth: np.ndarray, K: np.ndarray, up: np.ndarray | None = None, rgb: np.ndarray | None = None):
        """``(GravityEstimate, proposals)`` like the geometric proposer; needs ``rgb``. The
        gravity is ``up`` when given (with the floor measured along it), else estimated
        from the depth."""
        from ..gravity import gravity_with_floor

        if rgb is None:
            raise ValueError("the learned proposer needs the RGB frame")
        return gravity_with_floor(depth, K, up), self.detect(rgb, depth)
