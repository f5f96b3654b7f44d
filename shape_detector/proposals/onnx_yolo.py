"""External 2D proposals: a YOLO-style ONNX detector run with OpenCV DNN.

``OnnxYoloProposer(model_path)`` loads a user-supplied YOLOv5 / YOLOv8 ONNX export
(``cv2.dnn.readNetFromONNX``; no other runtime needed), letterboxes the RGB frame to
``input_size`` (grey 114 padding, RGB, values in [0, 1]), decodes either output layout

* YOLOv8: ``(1, 4 + nc, N)`` -- ``cx, cy, w, h`` then per-class scores,
* YOLOv5: ``(1, N, 5 + nc)`` -- ``cx, cy, w, h, objectness`` then per-class scores
  (score = objectness x class score),

(coordinates in letterboxed input pixels), keeps detections whose best class is one of
ours after :data:`COCO_TO_CLASS` (chair, couch -> sofa, bed, dining table -> table,
toilet; everything else is dropped), applies ``conf`` and class-wise NMS (``nms`` IoU)
and maps the boxes back to the original image as pixel-edge boxes.

``proposer.detect(rgb)`` gives the proposals; ``proposer(depth, K, up=None, rgb=None)``
has the geometric proposer's interface and also returns a gravity estimate (the given
``up`` or one estimated from the depth).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..classes import CLASSES
from . import Proposal

#: COCO-80 (0-based, as in YOLO exports) class id -> our class name.
COCO_TO_CLASS: dict[int, str] = {
    56: "chair",
    57: "sofa",  # couch
    59: "bed",
    60: "table",  # dining table
    61: "toilet",
}

assert all(v in CLASSES for v in COCO_TO_CLASS.values())


def letterbox(rgb: np.ndarray, size: int) -> tuple[np.ndarray, float, float, float]:
    """Resize keeping the aspect ratio and pad to ``size`` x ``size`` (value 114).

    Returns the padded image, the scale and the left / top padding in pixels: an input
    pixel coordinate ``q`` maps back to ``(q - pad) / scale``.
    """
    h, w = rgb.shape[:2]
    scale = min(size / h, size / w)
    nw, nh = int(round(w * scale)), int(round(h * scale))
    img = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR) if (nw, nh) != (w, h) else rgb
    px = (size - nw) / 2.0
    py = (size - nh) / 2.0
    left, top = int(round(px - 0.1)), int(round(py - 0.1))
    out = np.full((size, size, 3), 114, np.uint8)
    out[top : top + nh, left : left + nw] = img
    return out, scale, float(left), float(top)


def decode_yolo(
    out: np.ndarray, conf: float = 0.25, num_classes: int = 80
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes (M,4) ``x1 y1 x2 y2`` in input pixels, scores (M,), class ids (M,) of a raw
    YOLOv5 ``(1, N, 5 + nc)`` or YOLOv8 ``(1, 4 + nc, N)`` output above ``conf``."""
    a = np.asarray(out, dtype=np.float32)
    a = a.reshape(a.shape[-2], a.shape[-1]) if a.ndim == 3 else a
    if a.ndim != 2:
        raise ValueError(f"unexpected YOLO output shape {np.shape(out)}")
    c5, c4 = 5 + num_classes, 4 + num_classes
    if a.shape[1] in (c4, c5) and a.shape[0] not in (c4, c5):
        rows = a  # (N, C)
    elif a.shape[0] in (c4, c5) and a.shape[1] not in (c4, c5):
        rows = a.T
    elif a.shape[1] in (c4, c5):
        rows = a
    else:
        raise ValueError(f"YOLO output {np.shape(out)} has neither 4+{num_classes} nor 5+{num_classes} channels")
    if rows.shape[1] == c5:  # v5: objectness x class score
        cls_scores = rows[:, 5:] * rows[:, 4:5]
    else:
        cls_scores = rows[:, 4:]
    cid = np.argmax(cls_scores, axis=1)
    score = cls_scores[np.arange(len(rows)), cid]
    keep = score >= conf
    cx, cy, bw, bh = (rows[keep, i] for i in range(4))
    boxes = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], axis=1)
    return boxes, score[keep], cid[keep]


class OnnxYoloProposer:
    """Class-aware 2D proposals from a YOLOv5 / YOLOv8 ONNX model (OpenCV DNN, CPU).

    ``model_path``: the ``.onnx`` file; ``input_size``: the square network input (640 for
    standard exports); ``conf``: minimum score; ``nms``: IoU of the class-wise NMS;
    ``class_map``: model class id -> our class name (default COCO).
    """

    def __init__(
        self,
        model_path: str | Path,
        input_size: int = 640,
        conf: float = 0.25,
        nms: float = 0.45,
        class_map: dict[int, str] | None = None,
        num_classes: int = 80,
    ):
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model not found: {path}")
        self.model_path = path
        self.net = cv2.dnn.readNetFromONNX(str(path))
        self.input_size = int(input_size)
        self.conf = float(conf)
        self.nms = float(nms)
        self.class_map = dict(COCO_TO_CLASS if class_map is None else class_map)
        self.num_classes = int(num_classes)

    def raw_output(self, rgb: np.ndarray) -> tuple[np.ndarray, float, float, float]:
        """The network's output for one RGB uint8 frame, plus the letterbox scale / padding."""
        img, scale, left, top = letterbox(np.ascontiguousarray(rgb[..., :3]), self.input_size)
        blob = cv2.dnn.blobFromImage(img, 1.0 / 255.0, (self.input_size, self.input_size), swapRB=False, crop=False)
        self.net.setInput(blob)
        out = self.net.forward()
        if isinstance(out, (tuple, list)):
            out = out[0]
        return np.asarray(out), scale, left, top

    def detect(self, rgb: np.ndarray) -> list[Proposal]:
        """Proposals (our classes only) for an HxWx3 uint8 RGB frame, best first."""
        H, W = rgb.shape[:2]
        out, scale, left, top = self.raw_output(rgb)
        boxes, scores, cids = decode_yolo(out, self.conf, self.num_classes)
        mine = np.array([int(c) in self.class_map for c in cids], dtype=bool)
        boxes, scores, cids = boxes[mine], scores[mine], cids[mine]
        if len(boxes) == 0:
            return []
        # back to the original image, pixel edges, clipped
        boxes = (boxes - np.array([left, top, left, top], np.float32)) / scale
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, W)
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, H)
        ok = (boxes[:, 2] - boxes[:, 0] >= 1) & (boxes[:, 3] - boxes[:, 1] >= 1)
        boxes, scores, cids = boxes[ok], scores[ok], cids[ok]
        if len(boxes) == 0:
            return []
        xywh = [[float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])] for b in boxes]
        idx = cv2.dnn.NMSBoxesBatched(
            xywh, scores.astype(float).tolist(), cids.astype(int).tolist(), self.conf, self.nms
        )
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        idx = idx[np.argsort(-scores[idx], kind="stable")]
        return [
            Proposal(tuple(float(v) for v in boxes[i]), self.class_map[int(cids[i])], float(scores[i]), "onnx_yolo")
            for i in idx
        ]

    def __call__(
        self, depth: np.ndarray | None, K: np.ndarray, up: np.ndarray | None = None, rgb: np.ndarray | None = None
    ):
        """``(GravityEstimate, proposals)`` like the geometric proposer; needs ``rgb``."""
        from ..gravity import GravityEstimate, estimate_up

        if rgb is None:
            raise ValueError("OnnxYoloProposer needs the RGB frame")
        if up is not None:
            grav = GravityEstimate(np.asarray(up, np.float64) / np.linalg.norm(up), 1.0, "prior")
        elif depth is not None:
            grav = estimate_up(depth, K)
        else:
            grav = estimate_up(np.full(rgb.shape[:2], np.nan, np.float32), K)
        return grav, self.detect(rgb)
