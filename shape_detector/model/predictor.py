"""Inference wrapper: frustums in, camera-frame boxes + primitives + scores out.

One batched forward per call (frustums with different point counts are run as one
batch per count). Scores:

* class given (``class_ids[i]`` not None): ``class_name`` is the given class and
  ``score`` the calibrated objectness ``1 - p(background)``;
* class-agnostic (None): the one-hot is zeros, ``class_name`` is the argmax of the
  calibrated class probabilities over the foreground classes and ``score`` its probability.

The box size cluster is the given class, else the size head's argmax (as in Frustum
PointNets). Probabilities come from the temperature-scaled
softmax of the classification head (temperature stored in the weights). Weights trained
without the ``cls`` task fall back to the mean foreground probability of the predicted
foreground points as score. Frustums with no valid point get score 0.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..classes import CLASS_TO_ID, CLASSES
from ..frustum import Frustum
from ..geometry import rot_z, stretch_cuboids, wrap_angle
from ..types import Cuboid
from .config import PRECISIONS, ModelConfig
from .io import default_weights_path, load_weights
from .network import FrustumShapeNet
from .traced import TracedForward

BACKGROUND = "background"

#: ``precision="auto"``: batches of at least this many frustums run in bfloat16 on CPUs with
#: AMX, smaller ones in fp32 (bf16 has a fixed cost that only larger batches earn back)
AUTO_BF16_MIN_BATCH = 4


def bf16_min_batch(precision: str, device: torch.device) -> int | None:
    """The batch size from which a forward runs in bfloat16 under ``precision``: None =
    never (``"fp32"``, or ``"auto"`` on a device without AMX), 0 = always (``"bf16"``),
    :data:`AUTO_BF16_MIN_BATCH` for ``"auto"`` on a CPU with AMX."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "bf16":
        return 0
    if precision == "auto" and device.type == "cpu" and cpu_has_amx():
        return AUTO_BF16_MIN_BATCH
    return None


def cpu_has_amx() -> bool:
    """Whether this CPU has AMX tiles (bfloat16 matrix units); False when torch cannot tell."""
    try:
        return bool(torch.cpu._is_amx_tile_supported())
    except Exception:  # noqa: BLE001 - a private torch helper: absent means unknown
        return False


@dataclass
class FrustumPrediction:
    """Network output for one frustum; 3D quantities in the **camera** frame (metres).

    ``class_probs`` (num_classes+1,), background last; ``rotation`` columns = box axes
    (z column = gravity-up); ``primitives`` camera-frame cuboids after pruning;
    ``primitives_canonical`` the same in the canonical object frame (box centre, x =
    heading, z up, metres) for composing with another box (e.g. the GT one);
    ``seg_prob`` (N,) foreground probability of each frustum point; ``center_F`` /
    ``heading_F`` the box in the frustum frame. ``seg_features``: the network's
    class-independent segmentation features of this frustum (torch tensors, only with
    ``predict(..., keep_features=True)``), which let :meth:`FrustumPredictor.refine` skip the
    segmentation PointNet.
    """

    class_name: str
    class_probs: np.ndarray
    score: float
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    heading_U: float
    primitives: list[Cuboid]
    seg_prob: np.ndarray
    num_points_valid: int
    objectness: float = 0.0
    center_F: np.ndarray = field(default_factory=lambda: np.zeros(3))
    heading_F: float = 0.0
    primitives_canonical: list[Cuboid] = field(default_factory=list)
    seg_features: tuple[torch.Tensor, torch.Tensor] | None = field(default=None, repr=False, compare=False)


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"auto"``/None -> cuda when available else cpu; otherwise ``torch.device(device)``."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


#: the two passes of the mirrored test-time augmentation disagree about the box axes when
#: their headings differ by more than this modulo pi (radians); see :func:`merge_mirrored`
MIRROR_CONFLICT = np.pi / 4

_FLIP_Y = np.diag([1.0, -1.0, 1.0]).astype(np.float32)


def merge_mirrored(arr: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Merge the predictions on B frustums (first half of ``arr``, frame F) with those on the
    same frustums mirrored x -> -x (second half), as :meth:`FrustumPredictor.forward_arrays`
    arrays of batch 2B -> batch B.

    The mirrored centre gets its x negated and its heading ``t`` becomes ``pi - t``; its
    primitives (box-canonical) get their y negated. Class / segmentation probabilities are
    always averaged. The boxes:

    * headings within :data:`MIRROR_CONFLICT` of each other modulo pi: centres, sizes and
      headings are averaged (headings modulo pi when the two point opposite ways: the first
      prediction keeps the front); the primitives are the first prediction's, stretched to
      the averaged size;
    * otherwise the two passes disagree about the box axes (a box turned by ~90 degrees;
      sizes are not swapped to match, so it is not the same box), and the average would be
      a box ~45 degrees off both: the pass with the more confident heading bin
      (``heading_conf``) is kept whole.
    """
    n = arr["center"].shape[0] // 2
    a = {k: v[:n] for k, v in arr.items()}
    b = {k: v[n:] for k, v in arr.items()}
    out = dict(a)
    cb = b["center"].copy()
    cb[:, 0] *= -1.0
    hb = wrap_angle(np.pi - b["heading"])
    d = wrap_angle(hb - a["heading"])
    d = np.where(np.abs(d) > 0.5 * np.pi, wrap_angle(d + np.pi), d)  # opposite fronts: modulo pi
    conflict = np.abs(d) > MIRROR_CONFLICT
    take_b = conflict & (b["heading_conf"] > a["heading_conf"])
    keep_a = conflict & ~take_b
    out["center"] = np.where(take_b[:, None], cb, np.where(keep_a[:, None], a["center"], 0.5 * (a["center"] + cb)))
    out["heading"] = np.where(take_b, hb, wrap_angle(a["heading"] + np.where(conflict, 0.0, 0.5 * d))).astype(
        a["heading"].dtype
    )
    out["size"] = np.where(take_b[:, None], b["size"], np.where(keep_a[:, None], a["size"], 0.5 * (a["size"] + b["size"])))
    for key in ("probs", "seg_prob", "fg_score", "heading_conf"):
        out[key] = 0.5 * (a[key] + b[key])
    # primitives: the first prediction's, or the mirrored one's (y -> -y in the box frame) where it is kept
    base_c, base_s, base_r = a["prim_center"].copy(), a["prim_size"], a["prim_rotation"].copy()
    base_size = np.where(take_b[:, None], b["size"], a["size"])
    base_c[take_b] = b["prim_center"][take_b] * _FLIP_Y.diagonal()
    base_s = np.where(take_b[:, None, None], b["prim_size"], base_s)
    base_r[take_b] = _FLIP_Y @ b["prim_rotation"][take_b] @ _FLIP_Y
    ratio = out["size"] / np.maximum(base_size, 1e-9)  # (B, 3)
    out["prim_rotation"] = base_r
    out["prim_center"], out["prim_size"] = stretch_cuboids(base_c, base_s, base_r, ratio[:, None, :])
    return out


def refined_score(class_prob: float, objectness: float) -> float:
    """Score of a class-agnostic detection after its class-given second pass
    (:meth:`FrustumPredictor.refine`): the geometric mean of the first pass's probability of
    its class and the second pass's objectness (1 - background probability, given that
    class)."""
    return float(np.sqrt(max(class_prob, 0.0) * max(objectness, 0.0)))


class FrustumPredictor:
    """Loads weights once; :meth:`predict` runs one batched forward per call.

    ``weights``: a weights/checkpoint file; None uses the packaged
    ``shape_detector/weights/default.pt`` (falls back to a randomly initialised network
    with a warning when that file is missing -- outputs are then meaningless).
    ``device``: ``"cpu"``, ``"cuda"`` or ``"auto"``; ``num_threads`` sets torch's CPU threads.
    ``workers`` > 1 (CPU): a batch of at least ``2 * min_chunk`` frustums is split into
    that many chunks run on as many Python threads, each op single-threaded -- data
    parallelism without OpenMP's barrier waits (which make 2 intra-op threads slower than
    1 on a loaded 2-core machine). ``precision``: ``"fp32"`` (default), ``"bf16"``
    (bfloat16 autocast: about 2x faster on CPUs with AMX / AVX512-BF16 for large batches,
    much slower on those without; boxes differ slightly, see the README's speed section) or
    ``"auto"`` (bf16 for batches of at least :data:`AUTO_BF16_MIN_BATCH` frustums on a CPU
    with AMX, else fp32). ``trace`` (CPU): run the forward through frozen TorchScript graphs
    (:mod:`.traced`; same outputs, less overhead, and no GIL held while they run, which lets
    the node's two pipeline threads overlap); False = eager.
    """

    def __init__(
        self,
        weights: str | Path | None = None,
        device: str | torch.device = "cpu",
        num_threads: int | None = None,
        workers: int = 1,
        min_chunk: int = 3,
        precision: str = "fp32",
        trace: bool = True,
    ) -> None:
        self.precision = precision
        if num_threads is not None:
            torch.set_num_threads(int(num_threads))
        self.device = resolve_device(device)
        self._trace = bool(trace) and self.device.type == "cpu"
        #: the batch size from which forwards run in bfloat16 (None: never, 0: always)
        self.bf16_min_batch = bf16_min_batch(precision, self.device)
        self.workers = max(1, int(workers)) if self.device.type == "cpu" else 1
        self.min_chunk = max(1, int(min_chunk))
        self._pool = None
        self.meta: dict = {}
        if weights is None:
            p = default_weights_path()
            if p.is_file():
                weights = p
            else:
                warnings.warn(f"no packaged weights at {p}; using a randomly initialised network", stacklevel=2)
        if weights is None:
            torch.manual_seed(0)
            self.model = FrustumShapeNet(ModelConfig()).to(self.device).eval().fuse_batchnorm()
            self._forward = TracedForward(self.model, enabled=self._trace)
            self.weights_path = None
        else:
            self.load_weights(weights)

    def load_weights(self, path: str | Path) -> None:
        self.model, self.meta = load_weights(path, self.device)
        self.model.fuse_batchnorm()  # inference only: BatchNorm folded into the linear layers
        self._forward = TracedForward(self.model, enabled=self._trace)
        self.weights_path = Path(path)

    def warm_up(self, max_batch: int = 1) -> None:
        """Trace now, on dummy frustums, the graphs a frame may need (first pass and
        feature-reusing second pass, in each precision this predictor uses, with caches of
        either dtype), so that no camera frame pays the tracing; then run both passes once for
        every batch of 1 to ``max_batch`` frustums: the first call with a new batch size is
        slower (oneDNN builds its kernels per shape, eager or traced alike)."""
        n, nc = self.num_points, self.config.num_classes
        sizes = [1] if self.bf16_min_batch is None else [max(1, self.bf16_min_batch)]
        if self.bf16_min_batch:  # auto: small batches in fp32, large ones in bfloat16
            sizes = [1, self.bf16_min_batch]
        caches = []
        for b in sizes:
            out = self.forward_arrays(np.zeros((b, n, 6), np.float32), np.zeros((b, nc), np.float32), keep_features=True)
            caches.append((out["seg_glob"], out["seg_local"]))
        for b in sizes:
            for glob, local in caches:
                cache = (glob[:1].expand(b, *glob.shape[1:]), local[:1].expand(b, *local.shape[1:]))
                self.forward_arrays(np.zeros((b, n, 6), np.float32), np.eye(b, nc, dtype=np.float32), cache)
        dummy = Frustum(np.zeros((n, 6), np.float32), np.arange(n), 0, 0.0, np.eye(3))
        for b in range(1, int(max_batch) + 1):
            first = self.predict([dummy] * b, [None] * b, keep_features=True)
            self.predict([dummy] * b, [0] * b, seg_features=[p.seg_features for p in first])

    @property
    def config(self) -> ModelConfig:
        return self.model.config

    @property
    def num_points(self) -> int:
        """Points per frustum the network was trained with (extract frustums with this)."""
        return int(self.config.num_points)

    @property
    def has_class_head(self) -> bool:
        tasks = self.meta.get("tasks")
        return tasks is None or "cls" in tasks

    # --------------------------------------------------------------------------
    @torch.inference_mode()
    def forward_arrays(
        self,
        points: np.ndarray,
        one_hot: np.ndarray,
        seg_cache: tuple[torch.Tensor, torch.Tensor] | None = None,
        keep_features: bool = False,
    ) -> dict[str, np.ndarray]:
        """Raw batched forward on (B,N,6) points / (B,C) one-hot; decoded frame-F arrays.

        ``seg_cache``: the ``seg_glob`` / ``seg_local`` of an earlier call on the same points
        (the segmentation PointNet is skipped); ``keep_features`` adds them to the result
        (torch tensors, not arrays).
        """
        pts = torch.as_tensor(np.asarray(points, np.float32), device=self.device)
        oh = torch.as_tensor(np.asarray(one_hot, np.float32), device=self.device)
        bf16 = self.bf16_min_batch is not None and pts.shape[0] >= self.bf16_min_batch
        out = self._forward(pts, oh, seg_cache, bf16)
        seg_glob, seg_local = out.pop("seg_glob"), out.pop("seg_local")
        arrays: dict = {k: (v if v.device.type == "cpu" else v.cpu()).numpy() for k, v in out.items()}
        if keep_features:
            arrays["seg_glob"], arrays["seg_local"] = seg_glob, seg_local
        return arrays

    def predict(
        self,
        frustums: Sequence[Frustum],
        class_ids: Sequence[int | None] | None = None,
        mirror: bool = False,
        keep_features: bool = False,
        seg_features: Sequence[tuple[torch.Tensor, torch.Tensor] | None] | None = None,
    ) -> list[FrustumPrediction]:
        """Predictions for ``frustums`` (class ids: index into CLASSES, or None = unknown).

        ``mirror``: test-time augmentation; each frustum also runs mirrored (x -> -x in frame F,
        a symmetry the training augments with) in the same batch, and the two predictions are
        averaged (:func:`merge_mirrored`). Twice the network work.
        ``keep_features`` (no mirror): each prediction keeps its frustum's segmentation
        features (``FrustumPrediction.seg_features``); ``seg_features``: such features of an
        earlier pass over the same frustums, one per frustum (used where a whole
        same-size group has them, without mirror: that group skips the segmentation PointNet).
        """
        n = len(frustums)
        if class_ids is None:
            class_ids = [None] * n
        if len(class_ids) != n:
            raise ValueError("class_ids must match frustums")
        if n == 0:
            return []
        nc = self.config.num_classes
        results: list[FrustumPrediction | None] = [None] * n
        groups: dict[int, list[int]] = {}
        for i, f in enumerate(frustums):
            groups.setdefault(int(f.points.shape[0]), []).append(i)
        if seg_features is not None and len(seg_features) != n:
            raise ValueError("seg_features must match frustums")
        keep = keep_features and not mirror
        for _, idx in groups.items():
            pts = np.stack([frustums[i].points[:, :6] for i in idx]).astype(np.float32)
            oh = np.zeros((len(idx), nc), np.float32)
            for j, i in enumerate(idx):
                c = class_ids[i]
                if c is not None:
                    oh[j, int(c)] = 1.0
            cache = None
            if seg_features is not None and not mirror and all(seg_features[i] is not None for i in idx):
                cache = (
                    torch.stack([seg_features[i][0] for i in idx]),  # type: ignore[index]
                    torch.stack([seg_features[i][1] for i in idx]),  # type: ignore[index]
                )
            if mirror:
                flipped = pts.copy()
                flipped[..., 0] *= -1.0
                arr = merge_mirrored(self._forward_parallel(np.concatenate([pts, flipped]), np.concatenate([oh, oh])))
            else:
                arr = self._forward_parallel(pts, oh, cache, keep)
            for j, i in enumerate(idx):
                results[i] = self._decode_one(frustums[i], class_ids[i], arr, j)
                if keep:
                    results[i].seg_features = (arr["seg_glob"][j], arr["seg_local"][j])  # type: ignore[union-attr]
        return results  # type: ignore[return-value]

    def refine(
        self,
        frustums: Sequence[Frustum],
        first: Sequence[FrustumPrediction],
        mirror: bool = False,
        min_score: float = 0.0,
    ) -> list[FrustumPrediction]:
        """Class-given second pass for class-agnostic predictions ``first`` of ``frustums``.

        Each frustum whose first-pass score is at least ``min_score`` runs again with its
        predicted class as the one-hot (the input the network gets with external 2D
        detections, which gives it that class's size cluster and box prior): box,
        segmentation and primitives come from this pass, the class and its probabilities
        from ``first``. The score is the geometric mean of the first pass's class
        probability and the second pass's objectness, :func:`refined_score`. The others,
        those whose frustum has no valid point, and all of them when the weights have no
        class head, are returned unchanged.
        """
        if len(first) != len(frustums):
            raise ValueError("first must match frustums")
        idx = [
            i
            for i, p in enumerate(first)
            if p.class_name in CLASS_TO_ID and p.num_points_valid > 0 and p.score >= min_score
        ]
        out = list(first)
        if not idx or not self.has_class_head:
            return out
        second = self.predict(
            [frustums[i] for i in idx],
            [CLASS_TO_ID[first[i].class_name] for i in idx],
            mirror,
            seg_features=[first[i].seg_features for i in idx],
        )
        for i, q in zip(idx, second):
            p = first[i]
            out[i] = replace(q, class_name=p.class_name, class_probs=p.class_probs, score=refined_score(p.score, q.objectness))
        return out

    def _forward_parallel(
        self,
        pts: np.ndarray,
        oh: np.ndarray,
        seg_cache: tuple[torch.Tensor, torch.Tensor] | None = None,
        keep_features: bool = False,
    ) -> dict[str, np.ndarray]:
        """:meth:`forward_arrays`, split over ``self.workers`` threads for large batches."""
        n = pts.shape[0]
        k = min(self.workers, n // self.min_chunk)
        if k <= 1:
            return self.forward_arrays(pts, oh, seg_cache, keep_features)
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="frustum-net")
        bounds = np.linspace(0, n, k + 1).round().astype(int)
        futs = [
            self._pool.submit(
                self.forward_arrays,
                pts[a:b],
                oh[a:b],
                None if seg_cache is None else (seg_cache[0][a:b], seg_cache[1][a:b]),
                keep_features,
            )
            for a, b in zip(bounds[:-1], bounds[1:])
        ]
        parts = [f.result() for f in futs]
        return {
            key: (torch.cat if isinstance(parts[0][key], torch.Tensor) else np.concatenate)([p[key] for p in parts], 0)
            for key in parts[0]
        }

    def _decode_one(self, fr: Frustum, cid: int | None, arr: dict[str, np.ndarray], j: int) -> FrustumPrediction:
        cfg = self.config
        nc = cfg.num_classes
        probs = arr["probs"][j].astype(np.float64)
        objectness = float(1.0 - probs[nc])
        if cid is not None:
            cname = CLASSES[int(cid)]
            score = objectness
        else:
            k = int(np.argmax(probs[:nc]))
            cname = CLASSES[k]
            score = float(probs[k])
        if not self.has_class_head:
            score = float(arr["fg_score"][j])
        if fr.valid <= 0:
            score = 0.0
        R_cf = fr.R_cf
        center_F = arr["center"][j].astype(np.float64)
        heading_F = float(arr["heading"][j])
        size = arr["size"][j].astype(np.float64)
        R_box = R_cf @ rot_z(heading_F)
        center = R_cf @ center_F
        # primitives: prune low-volume ones (keep at least the largest)
        pc, ps, pr = arr["prim_center"][j], arr["prim_size"][j], arr["prim_rotation"][j]
        vol = np.prod(ps.astype(np.float64), axis=1)
        keep = vol >= cfg.prune_volume_frac * float(np.prod(size))
        if not keep.any():
            keep[int(np.argmax(vol))] = True
        canon = [Cuboid(pc[m], ps[m], pr[m]) for m in np.nonzero(keep)[0]]
        prims = [c.transformed(R_box, center) for c in canon]
        return FrustumPrediction(
            class_name=cname,
            class_probs=probs,
            score=float(np.clip(score, 0.0, 1.0)),
            center=center,
            size=size,
            rotation=R_box,
            heading_U=float(wrap_angle(heading_F - fr.phi)),
            primitives=prims,
            seg_prob=arr["seg_prob"][j].astype(np.float32),
            num_points_valid=int(fr.valid),
            objectness=objectness,
            center_F=center_F,
            heading_F=heading_F,
            primitives_canonical=canon,
        )
