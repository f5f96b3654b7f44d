"""The map's second opinion on a track's class and score (pure numpy).

A detection sees an object once, often in part; a track has seen it from many views. This
small multinomial logistic regression re-decides each published track's class (ten classes
or background) from what the map knows about the whole object:

* the accumulated class evidence (log probabilities, :attr:`SceneObject.class_probs`);
* the fused box: footprint long and short side and height (log metres, with their squares and
  pairwise products, so that a class's logit can be a Gaussian in log size), and its bottom's
  height above the floor (metres);
* how often and how surely it was detected (log observations, the track's score);
* its neighbours: for a few classes that furniture stands beside (a night stand by a bed, a
  chair at a desk or table), ``exp(-gap / 0.5 m)`` of the horizontal gap between the two
  boxes' bounding circles to the nearest other track of that class (0 without one).

Trained on final maps of generated walk-throughs that no evaluation uses
(``shape-detector train-track-classifier``; provenance in the weights file's ``meta``).
World frame: z up, metres.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ..classes import CLASSES
from .tracks import tracks_state

log = logging.getLogger(__name__)

#: the classes whose nearness is a feature (see the module docstring)
CONTEXT_CLASSES: tuple[str, ...] = ("bed", "chair", "table", "desk", "sofa", "toilet")
#: metres: the scale of the neighbour features' fall-off
CONTEXT_SCALE = 0.5
#: class probabilities are floored here before the log (evidence under 5% is not published)
PROB_FLOOR = 0.01
#: the feature names, in order
FEATURES: tuple[str, ...] = (
    *(f"log_p_{c}" for c in CLASSES), "log_length", "log_width", "log_height",
    "log_length^2", "log_width^2", "log_height^2", "log_length*log_width", "log_length*log_height",
    "log_width*log_height", "bottom_above_floor",
    "log_observations", "score", *(f"near_{c}" for c in CONTEXT_CLASSES))
#: the classifier's outputs: the ten classes, then background
OUTPUTS: tuple[str, ...] = (*CLASSES, "background")
#: file format version of the weights file
FORMAT_VERSION = 1
#: the log-size pairs multiplied into the quadratic features (long, short, height)
_QUAD_A, _QUAD_B = np.array([0, 1, 2, 0, 0, 1]), np.array([0, 1, 2, 1, 2, 2])
_CONTEXT_INDEX = np.array([CLASSES.index(c) for c in CONTEXT_CLASSES])


def default_path() -> Path:
    """The packaged weights file."""
    return Path(__file__).resolve().parent.parent / "weights" / "track_classifier.json"


def track_features(probs: np.ndarray, size: np.ndarray, center: np.ndarray, observations: np.ndarray,
                   score: np.ndarray, floor_z: float = 0.0) -> np.ndarray:
    """(N, len(FEATURES)) features of N tracks: ``probs`` (N, 10) accumulated class
    probabilities, ``size`` (N, 3) box extents (l, w, h; h along up), ``center`` (N, 3) world
    frame z up, ``observations`` (N,) detection counts, ``score`` (N,) the tracks' scores;
    ``floor_z`` world z of the floor. Metres."""
    probs = np.asarray(probs, float).reshape(-1, len(CLASSES))
    n = len(probs)
    size = np.asarray(size, float).reshape(n, 3)
    center = np.asarray(center, float).reshape(n, 3)
    out = np.empty((n, len(FEATURES)))
    nc = len(CLASSES)
    out[:, :nc] = np.log(np.maximum(probs, PROB_FLOOR))
    box = out[:, nc:nc + 3]
    box[:, 0] = np.maximum(size[:, 0], size[:, 1])
    box[:, 1] = np.minimum(size[:, 0], size[:, 1])
    box[:, 2] = size[:, 2]
    np.log(np.maximum(box, 0.05), out=box)
    out[:, nc + 3:nc + 9] = box[:, _QUAD_A] * box[:, _QUAD_B]
    out[:, nc + 9] = center[:, 2] - 0.5 * size[:, 2] - floor_z
    out[:, nc + 10] = np.log(np.maximum(np.asarray(observations, float).reshape(n), 1.0))
    out[:, nc + 11] = np.asarray(score, float).reshape(n)
    # neighbours: the gap between bounding circles to the nearest other track of each context class
    radius = 0.5 * np.hypot(size[:, 0], size[:, 1])
    d = center[:, None, :2] - center[None, :, :2]
    gap = np.maximum(np.sqrt((d * d).sum(2)) - radius[:, None] - radius[None, :], 0.0)
    np.fill_diagonal(gap, np.inf)
    of_class = probs.argmax(1)[:, None] == _CONTEXT_INDEX[None, :]  # (N, len(CONTEXT_CLASSES))
    nearest = np.where(of_class[None, :, :], gap[:, :, None], np.inf).min(1) if n else np.zeros((0, len(_CONTEXT_INDEX)))
    out[:, nc + 12:] = np.exp(-nearest / CONTEXT_SCALE)
    return out


def tracks_features(tracks: Sequence[Any], floor_z: float = 0.0,
                    state: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """:func:`track_features` of scene-map ``Track`` objects; ``state``: their
    :func:`~.tracks.tracks_state` when the caller has it already."""
    if not tracks:
        return np.zeros((0, len(FEATURES)))
    probs, score = tracks_state(tracks) if state is None else state
    return track_features(probs, np.array([t.size for t in tracks]), np.array([t.center for t in tracks]),
                          np.array([t.observations for t in tracks]), score, floor_z)


@dataclass(frozen=True)
class TrackClassifier:
    """Standardised features -> softmax over :data:`OUTPUTS` (see the module docstring)."""

    mean: np.ndarray
    scale: np.ndarray
    #: (len(FEATURES), len(OUTPUTS))
    weights: np.ndarray
    #: (len(OUTPUTS),)
    bias: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def probabilities(self, features: np.ndarray) -> np.ndarray:
        """(N, len(OUTPUTS)) class and background probabilities of :func:`track_features` rows."""
        z = (np.asarray(features, float) - self.mean) / self.scale
        logits = z @ self.weights + self.bias
        logits -= logits.max(1, keepdims=True)
        p = np.exp(logits)
        return p / p.sum(1, keepdims=True)

    def decide(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per row the decided class index (N,), its probability with background counted (the
        published score, N,) and the ten class probabilities renormalised without background (N, 10)."""
        p = self.probabilities(features)
        cls = p[:, : len(CLASSES)]
        k = cls.argmax(1)
        return k, cls[np.arange(len(k)), k], cls / np.maximum(cls.sum(1, keepdims=True), 1e-12)

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready file content (features and outputs named, so a file is checked on load)."""
        return {"format": FORMAT_VERSION, "features": list(FEATURES), "outputs": list(OUTPUTS),
                "mean": self.mean.tolist(), "scale": self.scale.tolist(), "weights": self.weights.tolist(),
                "bias": self.bias.tolist(), "meta": self.meta}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrackClassifier:
        """Raises ValueError when the file was written for other features or outputs."""
        if d.get("format") != FORMAT_VERSION or tuple(d.get("features", ())) != FEATURES \
                or tuple(d.get("outputs", ())) != OUTPUTS:
            raise ValueError("track classifier: the file's format, features or outputs are not this version's")
        w = np.asarray(d["weights"], float)
        if w.shape != (len(FEATURES), len(OUTPUTS)):
            raise ValueError(f"track classifier: weights of shape {w.shape}, expected {(len(FEATURES), len(OUTPUTS))}")
        return cls(np.asarray(d["mean"], float), np.asarray(d["scale"], float), w, np.asarray(d["bias"], float),
                   dict(d.get("meta", {})))

    def save(self, path: str | Path) -> None:
        """Write :meth:`to_dict` as JSON to ``path``."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> TrackClassifier:
        """Read a file :meth:`save` wrote (ValueError as :meth:`from_dict`)."""
        return cls.from_dict(json.loads(Path(path).read_text()))


def fit(features: np.ndarray, labels: np.ndarray, l2: float = 1e-3, meta: dict[str, Any] | None = None) -> TrackClassifier:
    """Fit by L-BFGS on the mean log loss plus ``l2`` times the squared weights. ``labels``
    (N,) indices into :data:`OUTPUTS`."""
    from scipy.optimize import minimize

    x = np.asarray(features, float)
    y = np.asarray(labels, int)
    if x.ndim != 2 or x.shape[1] != len(FEATURES) or len(y) != len(x) or len(y) == 0:
        raise ValueError(f"fit: features must be (N, {len(FEATURES)}) with N labels, N > 0")
    mean, scale = x.mean(0), x.std(0) + 1e-6
    z = (x - mean) / scale
    n, f = z.shape
    k = len(OUTPUTS)
    onehot = np.eye(k)[y]

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        W, b = w[: f * k].reshape(f, k), w[f * k:]
        logits = z @ W + b
        logits -= logits.max(1, keepdims=True)
        p = np.exp(logits)
        p /= p.sum(1, keepdims=True)
        value = -float(np.sum(onehot * np.log(p + 1e-12))) / n + l2 * float(np.sum(W * W))
        g = (p - onehot) / n
        return value, np.concatenate([(z.T @ g + 2 * l2 * W).ravel(), g.sum(0)])

    res = minimize(loss, np.zeros(f * k + k), jac=True, method="L-BFGS-B", options={"maxiter": 1000})
    return TrackClassifier(mean, scale, res.x[: f * k].reshape(f, k), res.x[f * k:], dict(meta or {}))


@lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int) -> TrackClassifier:
    return TrackClassifier.load(path)


def load_track_classifier(spec: str) -> TrackClassifier | None:
    """``SceneConfig.track_classifier``: "" or "none" -> None (off); "default" -> the packaged
    file (None, logged once, when the package has none); else a weights file (FileNotFoundError
    when missing, ValueError when it is not a track classifier of this version)."""
    if spec in ("", "none"):
        return None
    path = default_path() if spec == "default" else Path(spec)
    if not path.is_file():
        if spec == "default":
            _warn_missing(str(path))
            return None
        raise FileNotFoundError(f"track classifier {spec!r}: no such file")
    return _load_cached(str(path.resolve()), path.stat().st_mtime_ns)


@lru_cache(maxsize=1)
def _warn_missing(path: str) -> None:
    log.warning("track classifier: no packaged weights (%s); the class evidence decides", path)
