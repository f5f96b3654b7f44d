"""Evaluation report: report.md (tables), report.json (everything), PNG plots drawn with cv2.

:func:`write_report` takes the dict of :func:`shape_detector.evaluation.runner.evaluate`
(or a bare :func:`shape_detector.evaluation.ap.evaluate_detections` result) and writes

* ``report.md`` -- per-class AP at each IoU threshold + mAP; Table-4.1-style box errors
  per class; shape IoU / surface distance per class (camera and object frame); timing;
* ``report.json`` -- the results made JSON-safe by :func:`to_jsonable` (NaN -> null);
* ``pr_curves.png`` -- per-class precision/recall curves at 0.25 (or the first threshold),
  ``pr_curves_<thr>.png`` at each other threshold;
* ``ap_per_class.png`` -- bar chart of AP per class at each threshold.

No matplotlib: the plots are drawn on numpy canvases with OpenCV.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..classes import CLASSES, class_color

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BAR_COLORS = [(200, 120, 40), (40, 140, 230), (60, 170, 60), (160, 60, 160)]  # BGR


# ------------------------------------------------------------------------- helpers
def to_jsonable(obj: Any) -> Any:
    """``obj`` with numpy arrays/scalars turned into lists/floats/ints, tuples into lists,
    keys into strings and non-finite floats into None (strict JSON)."""
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if obj is None or isinstance(obj, str):
        return obj
    if hasattr(obj, "to_dict"):
        return to_jsonable(obj.to_dict())
    return str(obj)


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def fmt(v: Any, digits: int = 3, scale: float = 1.0, suffix: str = "") -> str:
    """A table cell: numbers with ``digits`` decimals (times ``scale``), '-' for missing/NaN."""
    if isinstance(v, Mapping):
        v = v.get("mean")
    if isinstance(v, str):
        return v
    f = _num(v)
    if f is None:
        return "-"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(int(v))
    return f"{f * scale:.{digits}f}{suffix}"


def markdown_table(rows: Sequence[Sequence[Any]], headers: Sequence[str]) -> str:
    """A GitHub-flavoured markdown table; cells go through :func:`fmt` unless already strings."""
    def cell(v: Any) -> str:
        return (v if isinstance(v, str) else fmt(v)).replace("|", "\\|").replace("\n", " ")

    head = "| " + " | ".join(cell(h) for h in headers) + " |"
    sep = "|" + "|".join("---" if i == 0 else "---:" for i in range(len(headers))) + "|"
    body = ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join([head, sep, *body]) + "\n"


def _bgr(name: str) -> tuple[int, int, int]:
    r, g, b = class_color(name)
    return int(b * 200), int(g * 200), int(r * 200)  # a bit darker: readable on white


def _text(img: np.ndarray, s: str, org: tuple[int, int], scale: float = 0.45, color=(0, 0, 0), thick: int = 1) -> None:
    cv2.putText(img, s, (int(org[0]), int(org[1])), _FONT, scale, color, thick, cv2.LINE_AA)


def _text_width(s: str, scale: float = 0.45, thick: int = 1) -> int:
    return int(cv2.getTextSize(s, _FONT, scale, thick)[0][0])


# --------------------------------------------------------------------------- plots
def draw_pr_curves(
    precision: Mapping[str, Sequence[float]],
    recall: Mapping[str, Sequence[float]],
    ap: Mapping[str, Any] | None = None,
    title: str = "",
    size: tuple[int, int] = (760, 560),
) -> np.ndarray:
    """BGR uint8 image of per-class precision/recall curves (classes with an empty or
    undefined curve are listed in the legend but not drawn)."""
    W, H = size
    img = np.full((H, W, 3), 255, np.uint8)
    left, right, top, bottom = 60, 200, 40, 50
    pw, ph = W - left - right, H - top - bottom

    def xy(r: float, p: float) -> tuple[int, int]:
        return int(round(left + r * pw)), int(round(top + (1.0 - p) * ph))

    for t in np.linspace(0, 1, 6):
        cv2.line(img, xy(t, 0), xy(t, 1), (225, 225, 225), 1)
        cv2.line(img, xy(0, t), xy(1, t), (225, 225, 225), 1)
        _text(img, f"{t:.1f}", (xy(t, 0)[0] - 10, xy(t, 0)[1] + 18), 0.4)
        _text(img, f"{t:.1f}", (left - 32, xy(0, t)[1] + 4), 0.4)
    cv2.rectangle(img, xy(0, 1), xy(1, 0), (0, 0, 0), 1)
    _text(img, "recall", (left + pw // 2 - 20, H - 10), 0.5)
    _text(img, "precision", (4, top - 12), 0.5)
    _text(img, title, (left + 70, top - 14), 0.55)
    ly = top + 10
    for cls in precision:
        p = np.asarray(precision.get(cls, []), dtype=np.float64)
        r = np.asarray(recall.get(cls, []), dtype=np.float64)
        color = _bgr(cls)
        ok = p.size > 0 and r.size == p.size and np.all(np.isfinite(r))
        if ok:
            pts = np.array([xy(0.0, p[0])] + [xy(a, b) for a, b in zip(r, p)], np.int32)
            cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA)
        a = None if ap is None else _num(ap.get(cls))
        label = f"{cls} {a:.3f}" if a is not None else f"{cls} -"
        cv2.line(img, (W - right + 12, ly - 4), (W - right + 36, ly - 4), color, 3 if ok else 1)
        _text(img, label, (W - right + 42, ly), 0.42)
        ly += 20
    return img


def draw_bar_chart(
    series: Mapping[str, Mapping[str, Any]],
    classes: Sequence[str],
    title: str = "",
    size: tuple[int, int] = (900, 460),
    ymax: float = 1.0,
) -> np.ndarray:
    """BGR uint8 grouped bar chart: ``series[name][cls]`` values in [0, ymax] (None/NaN -> no bar)."""
    W, H = size
    img = np.full((H, W, 3), 255, np.uint8)
    left, right, top, bottom = 50, 20, 50, 50
    pw, ph = W - left - right, H - top - bottom
    base = top + ph
    for t in np.linspace(0, ymax, 6):
        y = int(round(base - t / ymax * ph))
        cv2.line(img, (left, y), (left + pw, y), (225, 225, 225), 1)
        _text(img, f"{t:.1f}", (8, y + 4), 0.4)
    cv2.line(img, (left, base), (left + pw, base), (0, 0, 0), 1)
    cv2.line(img, (left, top), (left, base), (0, 0, 0), 1)
    _text(img, title, (left, 22), 0.55)
    names = list(series)
    ncls = max(len(classes), 1)
    group = pw / ncls
    bar = group * 0.8 / max(len(names), 1)
    for i, cls in enumerate(classes):
        x0 = left + i * group + group * 0.1
        for j, name in enumerate(names):
            v = _num(series[name].get(cls))
            if v is None:
                continue
            x1 = int(round(x0 + j * bar))
            y1 = int(round(base - min(max(v, 0.0), ymax) / ymax * ph))
            cv2.rectangle(img, (x1, y1), (int(round(x1 + bar)) - 1, base), _BAR_COLORS[j % len(_BAR_COLORS)], -1)
            if bar >= 22:
                label = f"{v:.2f}"
                _text(img, label, (int(x1 + (bar - _text_width(label, 0.33)) / 2), y1 - 4), 0.33)
        label = cls if _text_width(cls, 0.4) <= group else cls[: max(3, int(group // 8))]
        _text(img, label, (int(left + i * group + (group - _text_width(label, 0.4)) / 2), base + 18), 0.4)
    lx = W - right - 10
    for j, name in reversed(list(enumerate(names))):
        w = _text_width(name, 0.45)
        lx -= w + 30
        cv2.rectangle(img, (lx, 28), (lx + 16, 40), _BAR_COLORS[j % len(_BAR_COLORS)], -1)
        _text(img, name, (lx + 20, 40), 0.45)
    return img


# ---------------------------------------------------------------------------- report
def _detection_part(results: Mapping[str, Any]) -> Mapping[str, Any] | None:
    if "detection" in results and isinstance(results["detection"], Mapping):
        return results["detection"]
    return results if "ap" in results else None


def _ap_section(det: Mapping[str, Any], classes: Sequence[str]) -> list[str]:
    keys = list(det.get("ap", {}))
    headers = ["class", "#GT", "#ignored", "#det"] + [f"AP@{k}" for k in keys]
    rows = []
    for c in classes:
        rows.append(
            [c, det.get("num_gt", {}).get(c, 0), det.get("num_ignored_gt", {}).get(c, 0), det.get("num_det", {}).get(c, 0)]
            + [det["ap"][k].get(c) for k in keys]
        )
    rows.append(["**mAP**", "", "", ""] + [det.get("mAP", {}).get(k) for k in keys])
    return ["## Detection AP (3D IoU)", "", markdown_table(rows, headers),
            "mAP is the mean over the classes that have ground truth ('-': no GT).", ""]


def _rows_with_pairs(per: Mapping[str, Any], classes: Sequence[str]) -> list[tuple[str, Mapping[str, Any]]]:
    return [(c, per[c]) for c in classes if isinstance(per.get(c), Mapping) and per[c].get("n", 0)]


def _box_section(box: Mapping[str, Any], classes: Sequence[str]) -> list[str]:
    headers = ["class", "n", "seg acc", "centroid (m)", "size abs (m)", "size rel (%)", "heading (deg)",
               "heading mod 180 (deg)", "corner (m)", "corner flip-inv (m)", "3D IoU"]
    per = dict(box.get("per_class", {}))
    rows = []
    for name, s in _rows_with_pairs(per, classes) + [("**all**", box.get("all", {"n": 0}))]:
        rows.append([
            name, s.get("n", 0), s.get("seg_accuracy"), s.get("centroid_error"), s.get("size_abs_error"),
            fmt(s.get("size_rel_error"), 1, 100.0), fmt(s.get("heading_error_deg"), 1),
            fmt(s.get("heading_error_sym_deg"), 1), s.get("corner_error"), s.get("corner_error_flip"),
            s.get("iou3d"),
        ])
    lines = ["## Box errors (thesis Table 4.1 style, means over pairs; classes without pairs omitted)", ""]
    if box.get("pairing"):
        lines += [f"Pairs: {box['pairing']}.", ""]
    return lines + [markdown_table(rows, headers), ""]


def _shape_section(shape: Mapping[str, Any], classes: Sequence[str]) -> list[str]:
    headers = ["class", "n", "IoU (camera)", "surf. dist (camera)", "IoU (object)", "surf. dist (object)",
               "IoU (box-relative)"]
    per = dict(shape.get("per_class", {}))
    rows = []
    extra = [("**all**", shape.get("all", {"n": 0}))]
    if isinstance(shape.get("class_mean"), Mapping):
        extra.append(("**class mean**", shape["class_mean"]))
    for name, s in _rows_with_pairs(per, classes) + extra:
        rows.append([name, s.get("n", 0), s.get("iou_camera"), s.get("distance_camera"),
                     s.get("iou_object"), s.get("distance_object"), s.get("iou_box")])
    lines = ["## Shape primitives vs GT parts (means over pairs; classes without pairs omitted; "
             "'class mean' averages the class rows)", ""]
    if shape.get("note"):
        lines += [str(shape["note"]), ""]
    return lines + [markdown_table(rows, headers), ""]


def _timing_section(t: Mapping[str, Any]) -> list[str]:
    rows = []
    for k, v in t.items():
        if isinstance(v, (list, tuple, Mapping)):
            continue
        if k.endswith("_s") and k != "total_s":
            rows.append([k[:-2] + " (ms)", fmt(_num(v), 1, 1000.0)])
        else:
            rows.append([k, v])
    return ["## Timing", "", markdown_table(rows, ["quantity", "value"]), ""]


def write_report(results: Mapping[str, Any], out_dir: str | Path, title: str = "Evaluation") -> dict[str, Path]:
    """Write report.md, report.json and the PNG plots into ``out_dir`` (created).

    Returns ``{"markdown": path, "json": path, "pr_curves": path, ...}``; missing
    sections of ``results`` are simply left out.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    det = _detection_part(results)
    classes = list((det or {}).get("classes") or results.get("classes") or CLASSES)

    md = [f"# {title}", ""]
    settings = results.get("settings")
    if isinstance(settings, Mapping) and settings:
        md += ["## Settings", "", markdown_table([[k, str(to_jsonable(v))] for k, v in settings.items()],
                                                 ["setting", "value"]), ""]
    if det is not None:
        md += _ap_section(det, classes)
    hyp = results.get("detection_class_hypotheses")
    if isinstance(hyp, Mapping) and hyp.get("ap"):
        keys = list(hyp["ap"])
        rows = [[c] + [hyp["ap"][k].get(c) for k in keys] for c in classes]
        rows.append(["**mAP**"] + [hyp.get("mAP", {}).get(k) for k in keys])
        md += [f"## Detection AP, each box counted for its top {hyp.get('k')} classes", "",
               "VoteNet-style per-class proposals: every detection is also scored for its runner-up "
               "classes (by their probability). The table above (one class per box) is what the "
               "detector outputs.", "", markdown_table(rows, ["class"] + [f"AP@{k}" for k in keys]), ""]
    if isinstance(results.get("box_errors"), Mapping):
        md += _box_section(results["box_errors"], classes)
    if isinstance(results.get("shape"), Mapping):
        md += _shape_section(results["shape"], classes)
    if isinstance(results.get("timing"), Mapping):
        md += _timing_section(results["timing"])

    if det is not None and det.get("ap"):
        keys = list(det["ap"])
        main_key = "0.25" if "0.25" in keys else keys[0]
        for k in keys:
            img = draw_pr_curves(det.get("precision", {}).get(k, {}), det.get("recall", {}).get(k, {}),
                                 det["ap"][k], title=f"{title}: PR @ 3D IoU {k}")
            # the main threshold's plot is written once, under the name the markdown links
            p = out / ("pr_curves.png" if k == main_key else f"pr_curves_{k}.png")
            cv2.imwrite(str(p), img)
            paths[f"pr_curves_{k}"] = p
        paths["pr_curves"] = paths[f"pr_curves_{main_key}"]
        bars = draw_bar_chart({f"AP@{k}": det["ap"][k] for k in keys}, classes, title=f"{title}: AP per class")
        paths["ap_bar"] = out / "ap_per_class.png"
        cv2.imwrite(str(paths["ap_bar"]), bars)
        md += ["## Plots", "", "![PR curves](pr_curves.png)", "", "![AP per class](ap_per_class.png)", ""]

    paths["markdown"] = out / "report.md"
    paths["markdown"].write_text("\n".join(md))
    paths["json"] = out / "report.json"
    paths["json"].write_text(json.dumps(to_jsonable(results), indent=1, allow_nan=False))
    return paths
