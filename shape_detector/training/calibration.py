"""Class-head temperature calibration and calibration statistics."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def fit_temperature(logits: np.ndarray, labels: np.ndarray) -> float:
    """Temperature minimising the NLL of ``softmax(logits / T)`` (1D search, log-spaced)."""
    if len(labels) == 0:
        return 1.0
    lg = torch.as_tensor(logits, dtype=torch.float64)
    lb = torch.as_tensor(labels, dtype=torch.long)

    def nll(T: float) -> float:
        return float(torch.nn.functional.cross_entropy(lg / T, lb))

    grid = np.exp(np.linspace(np.log(0.05), np.log(20.0), 121))
    vals = [nll(T) for T in grid]
    i = int(np.argmin(vals))
    lo, hi = grid[max(0, i - 1)], grid[min(len(grid) - 1, i + 1)]
    fine = np.exp(np.linspace(np.log(lo), np.log(hi), 41))
    vals = [nll(T) for T in fine]
    return float(fine[int(np.argmin(vals))])


def calibration_stats(probs: np.ndarray, labels: np.ndarray, bins: int = 15) -> dict[str, float]:
    """Accuracy, NLL and expected calibration error (top-1 confidence, equal-width bins)."""
    if len(labels) == 0:
        return {"acc": float("nan"), "nll": float("nan"), "ece": float("nan")}
    conf = probs.max(1)
    pred = probs.argmax(1)
    correct = (pred == labels).astype(np.float64)
    edges = np.linspace(0, 1, bins + 1)
    ece = 0.0
    for i in range(bins):
        m = (conf > edges[i]) & (conf <= edges[i + 1])
        if m.any():
            ece += m.mean() * abs(correct[m].mean() - conf[m].mean())
    nll = float(-np.mean(np.log(np.clip(probs[np.arange(len(labels)), labels], 1e-12, 1))))
    return {"acc": float(correct.mean()), "nll": nll, "ece": float(ece)}


def softmax_np(x: np.ndarray, T: float = 1.0) -> np.ndarray:
    """Row softmax of ``x / T``."""
    z = x / T
    z = z - z.max(1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(1, keepdims=True)


def calibrate(raw: dict[str, np.ndarray]) -> dict[str, Any]:
    """Fit the class-head temperature on validation logits (both one-hot modes)."""
    logits = np.concatenate([raw["logits_agn"], raw["logits_given"]])
    labels = np.concatenate([raw["labels"], raw["labels"]])
    T = fit_temperature(logits, labels)
    out: dict[str, Any] = {"temperature": T}
    for tag in ("agn", "given"):
        sfx = "agnostic" if tag == "agn" else "given"
        out[f"before_{sfx}"] = calibration_stats(softmax_np(raw[f"logits_{tag}"]), raw["labels"])
        out[f"after_{sfx}"] = calibration_stats(softmax_np(raw[f"logits_{tag}"], T), raw["labels"])
    return out
