"""Training logs: ``log.json`` / ``log.csv`` and the loss-curve picture ``loss_curve.png``."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

_W, _H, _PAD = 560, 360, 50
_COLORS = [(200, 30, 30), (30, 140, 30), (30, 30, 200), (200, 130, 0), (150, 0, 150), (0, 150, 150),
           (90, 90, 90), (0, 90, 200), (200, 0, 90), (120, 60, 0), (0, 0, 0), (60, 160, 60)]
_TRAIN_KEYS = ["total", "seg", "center", "corner", "heading_cls", "size_res", "box2_corner", "coverage", "consistency",
               "part", "volume", "occupancy", "cls"]
_VAL_KEYS = ["seg_acc", "box_iou", "box_acc25", "box_acc50", "box_iou_agnostic", "shape_iou", "shape_iou_gtbox",
             "cls_acc_agnostic", "heading_acc_30deg"]


def _axes(img: np.ndarray, x0: int, title: str, lims: tuple[float, float, float, float], log_y: bool) -> None:
    import cv2

    xmin, xmax, ymin, ymax = lims
    cv2.putText(img, title, (x0 + _PAD, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    L, T, R, B = x0 + _PAD, 30, x0 + _W - 15, _H - 20
    cv2.rectangle(img, (L, T), (R, B), (0, 0, 0), 1)
    for j in range(5):
        yv = ymin + (ymax - ymin) * j / 4
        yy = int(B - (B - T) * j / 4)
        lab = f"{10 ** yv:.3g}" if log_y else f"{yv:.2f}"
        cv2.putText(img, lab, (x0 + 2, yy + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (60, 60, 60), 1, cv2.LINE_AA)
        cv2.line(img, (L, yy), (R, yy), (225, 225, 225), 1)
    cv2.putText(img, f"{xmin:.0f}", (L, B + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (60, 60, 60), 1)
    cv2.putText(img, f"{xmax:.0f}", (R - 30, B + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (60, 60, 60), 1)


def _panel(img: np.ndarray, x0: int, title: str, series: list, log_y: bool) -> None:
    """One plot of ``series`` = [(name, xs, ys)] at column ``x0`` of ``img``."""
    import cv2

    def tf(v: np.ndarray) -> np.ndarray:
        return np.log10(np.maximum(v, 1e-6)) if log_y else v

    ally = np.concatenate([np.asarray(ys, float) for _, _, ys in series]) if series else np.zeros(0)
    allx = np.concatenate([np.asarray(xs, float) for _, xs, _ in series]) if series else np.zeros(0)
    ok = np.isfinite(ally) & ((ally > 0) if log_y else True)
    if not ok.any():
        return
    ymin, ymax = float(tf(ally[ok]).min()), float(tf(ally[ok]).max())
    ymax = ymax if ymax - ymin >= 1e-6 else ymin + 1
    xmin, xmax = float(allx.min()), float(allx.max())
    xmax = xmax if xmax - xmin >= 1e-9 else xmin + 1
    _axes(img, x0, title, (xmin, xmax, ymin, ymax), log_y)
    L, T, R, B = x0 + _PAD, 30, x0 + _W - 15, _H - 20
    for i, (name, xs, ys) in enumerate(series):
        xs, ys = np.asarray(xs, float), np.asarray(ys, float)
        good = np.isfinite(ys) & ((ys > 0) if log_y else True)
        xs, ys = xs[good], ys[good]
        col = _COLORS[i % len(_COLORS)]
        if len(xs) == 0:
            continue
        px = (L + (xs - xmin) / (xmax - xmin) * (R - L)).astype(np.int32)
        py = (B - (tf(ys) - ymin) / (ymax - ymin) * (B - T)).astype(np.int32)
        if len(px) > 1:
            cv2.polylines(img, [np.stack([px, py], 1).reshape(-1, 1, 2)], False, col, 1, cv2.LINE_AA)
        else:
            cv2.circle(img, (int(px[0]), int(py[0])), 3, col, -1)
        cv2.putText(img, name, (L + 8 + 130 * (i % 4), _H + 2 + 12 * (i // 4)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.38, col, 1, cv2.LINE_AA)


def _series(rows: list[dict[str, Any]], keys: list[str], xkey: str) -> list:
    out = []
    for k in keys:
        xs = [r[xkey] for r in rows if k in r]
        if xs:
            out.append((k, xs, [r[k] for r in rows if k in r]))
    return out


def plot_curves(history: dict[str, Any], path: str | Path) -> None:
    """Loss curves (train, per logged step, log scale) and validation metrics per epoch (cv2)."""
    import cv2

    img = np.full((_H + 30, 2 * _W, 3), 255, np.uint8)
    _panel(img, 0, "train losses (per logged step, log)", _series(history.get("steps", []), _TRAIN_KEYS, "step"), True)
    _panel(img, _W, "validation (per epoch)", _series(history.get("epochs", []), _VAL_KEYS, "epoch"), False)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def write_logs(out_dir: Path, history: dict[str, Any], meta: dict[str, Any]) -> None:
    """``log.json`` (meta, epochs, steps), ``log.csv`` (one row per epoch) and the curves."""
    rows = history.get("epochs", [])
    with open(out_dir / "log.json", "w") as f:
        json.dump({"meta": meta, "epochs": rows, "steps": history.get("steps", [])}, f, indent=1)
    if rows:
        keys: list[str] = []
        for r in rows:
            keys += [k for k in r if k not in keys]
        with open(out_dir / "log.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    try:
        plot_curves(history, out_dir / "loss_curve.png")
    except Exception as e:  # plotting must never kill a run
        print(f"warning: loss curve not written: {e}")


def fmt_eta(sec: float) -> str:
    """Seconds as ``h:mm:ss``."""
    sec = max(0, int(sec))
    return f"{sec // 3600:d}:{sec % 3600 // 60:02d}:{sec % 60:02d}"
