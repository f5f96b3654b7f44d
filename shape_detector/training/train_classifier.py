"""Training of the proposal classifier on candidates from :mod:`.classifier_data`.

Whole frames are held out for model selection and temperature calibration (a fraction
of the candidates' frames, ``val_fraction``). Loss: cross-entropy over the ten classes and
background, each row weighted by its ``weight`` (0 = "don't care") times a class weight
``(n_max / n_c) ** class_balance`` (the AP is a mean over classes, so rare ones count as
much as chairs). Augmentation: the frustum mirrored (x -> -x, which swaps the 2D box's
left and right border flags), as the frustum network trains with.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..classes import NUM_CLASSES
from ..model.classifier import GLOBAL_FEATURES, ClassifierConfig, ProposalClassifier, save_classifier
from .frustum_dataset import split_frames

_CUT_LEFT, _CUT_RIGHT = GLOBAL_FEATURES.index("cut_left"), GLOBAL_FEATURES.index("cut_right")


@dataclass
class ClassifierTrainConfig:
    """Training settings of the proposal classifier (a recipe's classifier phase ``train``)."""

    epochs: int = 12
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-4
    val_fraction: float = 0.1
    class_balance: float = 0.5
    seed: int = 0
    threads: int = 1


def class_weights(labels: np.ndarray, weights: np.ndarray, power: float) -> np.ndarray:
    """``(n_max / n_c) ** power`` per class (C+1,), counting rows of positive weight."""
    n = np.bincount(labels[weights > 0], minlength=NUM_CLASSES + 1).astype(np.float64)
    return np.where(n > 0, (n.max() / np.maximum(n, 1.0)) ** power, 0.0)


def mirror(points: torch.Tensor, globals_: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The candidates mirrored x -> -x in the frustum frame."""
    p = points.clone()
    p[..., 0] = -p[..., 0]
    g = globals_.clone()
    g[:, [_CUT_LEFT, _CUT_RIGHT]] = g[:, [_CUT_RIGHT, _CUT_LEFT]]
    return p, g


@torch.no_grad()
def predict_logits(model: ProposalClassifier, points: np.ndarray, globals_: np.ndarray, batch: int = 256) -> torch.Tensor:
    """Untempered logits, eval mode, on evenly spaced points as at inference."""
    model.eval()
    n = points.shape[1] if points.ndim == 3 else 0
    sel = np.linspace(0, n - 1, min(n, model.config.num_points)).round().astype(np.int64)
    out = []
    for a in range(0, len(points), batch):
        out.append(model(torch.as_tensor(points[a:a + batch][:, sel], dtype=torch.float32),
                         torch.as_tensor(globals_[a:a + batch], dtype=torch.float32)))
    return torch.cat(out) if out else torch.zeros(0, NUM_CLASSES + 1)


def fit_temperature(logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor) -> float:
    """The temperature minimising the weighted NLL (golden-section search over log T)."""
    def nll(log_t: float) -> float:
        loss = F.cross_entropy(logits / math.exp(log_t), labels, reduction="none")
        return float((loss * weights).sum() / weights.sum().clamp_min(1e-9))

    lo, hi = math.log(0.25), math.log(4.0)
    g = (math.sqrt(5) - 1) / 2
    for _ in range(40):
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        if nll(a) < nll(b):
            hi = b
        else:
            lo = a
    return math.exp(0.5 * (lo + hi))


def evaluate_rows(model: ProposalClassifier, ds: dict[str, np.ndarray], rows: np.ndarray) -> dict[str, float]:
    """Weighted NLL (at the model's temperature), accuracy, and object-vs-background accuracy."""
    logits = predict_logits(model, ds["points"][rows], ds["globals"][rows])
    y = torch.as_tensor(ds["label"][rows].astype(np.int64))
    w = torch.as_tensor(ds["weight"][rows])
    T = float(model.temperature)
    nll = float((F.cross_entropy(logits / T, y, reduction="none") * w).sum() / w.sum().clamp_min(1e-9))
    pred = logits.argmax(1)
    keep = w > 0
    fg = y < NUM_CLASSES
    return {
        "nll": nll,
        "acc": float((pred[keep] == y[keep]).float().mean()),
        "acc_objects": float((pred[keep & fg] == y[keep & fg]).float().mean()),
        "objectness_acc": float(((pred[keep] < NUM_CLASSES) == fg[keep]).float().mean()),
    }


def train_classifier(
    ds: dict[str, np.ndarray],
    out: str | Path,
    config: ClassifierTrainConfig | None = None,
    model_config: ClassifierConfig | None = None,
    log: Callable[[str], None] = print,
    provenance: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train on the candidate arrays ``ds``; writes ``out`` (the best epoch's weights, by
    held-out NLL, temperature-calibrated, with ``provenance`` and its metrics) and returns the log."""
    cfg = config or ClassifierTrainConfig()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    tr, va = split_frames(ds["frame_index"], cfg.val_fraction, cfg.seed)
    tr = tr[ds["weight"][tr] > 0]
    model = ProposalClassifier(model_config)
    cw = torch.as_tensor(class_weights(ds["label"][tr], ds["weight"][tr], cfg.class_balance), dtype=torch.float32)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps = cfg.epochs * max(1, len(tr) // cfg.batch_size)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=steps, pct_start=0.1)
    best: dict[str, Any] = {"nll": float("inf")}
    history = []
    step = 0
    for epoch in range(cfg.epochs):
        model.train()
        t0 = time.time()
        order = rng.permutation(tr)
        total = 0.0
        for a in range(0, len(order) - cfg.batch_size + 1, cfg.batch_size):
            if step >= steps:
                break
            rows = np.sort(order[a:a + cfg.batch_size])
            pts = ds["points"][rows]
            if pts.shape[1] > model.config.num_points:  # a random subset of each frustum's points
                pick = np.argsort(rng.random((len(rows), pts.shape[1])), axis=1)[:, : model.config.num_points]
                pts = np.take_along_axis(pts, pick[..., None], axis=1)
            p = torch.as_tensor(pts, dtype=torch.float32)
            g = torch.as_tensor(ds["globals"][rows], dtype=torch.float32)
            flip = torch.as_tensor(rng.random(len(rows)) < 0.5)
            if flip.any():
                pm, gm = mirror(p[flip], g[flip])
                p[flip], g[flip] = pm, gm
            y = torch.as_tensor(ds["label"][rows].astype(np.int64))
            w = torch.as_tensor(ds["weight"][rows]) * cw[y]
            loss = (F.cross_entropy(model(p, g), y, reduction="none") * w).sum() / w.sum().clamp_min(1e-9)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            total += float(loss.detach()) * len(rows)
        model.temperature.fill_(1.0)
        logits = predict_logits(model, ds["points"][va], ds["globals"][va])
        yv = torch.as_tensor(ds["label"][va].astype(np.int64))
        wv = torch.as_tensor(ds["weight"][va])
        model.temperature.fill_(fit_temperature(logits, yv, wv))
        metrics = evaluate_rows(model, ds, va)
        row = {"epoch": epoch + 1, "train_loss": total / max(1, len(order)), "temperature": float(model.temperature),
               "seconds": time.time() - t0, **metrics}
        history.append(row)
        log(" ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
        if metrics["nll"] < best["nll"]:
            best = dict(row)
            save_classifier(model, out, meta={"train_config": asdict(cfg), "history": history, "best": best,
                                              "features": list(GLOBAL_FEATURES)},
                            provenance={**(provenance or {}), "metrics": best})
    return {"best": best, "history": history}
