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
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..classes import CLASS_TO_ID, CLASSES
from ..frustum import Frustum
from ..geometry import rot_z, wrap_angle
from ..types import Cuboid
from .config import PRECISIONS, ModelConfig
from .batching import MIRROR_CONFLICT, concat as _concat, merge_mirrored, repeat_first as _repeat_first, stack as _stack
from .devices import bf16_min_batch, resolve_device
from .onnx_backend import resolve_backend
from .onnx_quantize import HEAD_PASSES, int8_graphs, quantized_graphs, quantized_passes
from .prediction import FrustumPrediction, refined_score

if TYPE_CHECKING:
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from .onnx_backend import OrtFrustumForward

BACKGROUND = "background"

def default_weights_path() -> Path:
    """The packaged weights ``shape_detector/weights/default.pt`` (may not exist); as
    :func:`shape_detector.model.io.default_weights_path`, without importing torch."""
    return Path(__file__).resolve().parents[1] / "weights" / "default.pt"


__all__ = ["FrustumPrediction", "FrustumPredictor", "MIRROR_CONFLICT", "merge_mirrored", "refined_score"]


class FrustumPredictor:
    """Loads weights once; :meth:`predict` runs one batched forward per call.

    ``weights``: a weights/checkpoint file; None uses the packaged
    ``shape_detector/weights/default.pt`` (falls back to a randomly initialised network
    with a warning when that file is missing -- outputs are then meaningless).
    ``device``: ``"cpu"``, ``"cuda"`` or ``"auto"``. ``backend``: ``"auto"`` (default: ONNX
    Runtime where installed, see :mod:`.onnx_backend`), ``"onnxruntime"`` or ``"torch"``; the
    onnxruntime graphs are exported once per weights file and cached (:mod:`.onnx_export`),
    and a predictor that finds them cached never imports torch. ``num_threads``: intra-op
    threads of torch / of each onnxruntime session (None: torch's default, one session thread).
    ``workers`` > 1 (CPU): a batch of at least ``2 * min_chunk`` frustums is split into
    up to that many chunks run on as many Python threads, each single-threaded -- data
    parallelism without OpenMP's barrier waits (which make 2 intra-op threads slower than
    1 on a loaded 2-core machine); both backends release the GIL while a graph runs.
    ``precision`` (torch): ``"fp32"`` (default), ``"bf16"`` (bfloat16 autocast: about 2x
    faster on CPUs with AMX / AVX512-BF16 for large batches, much slower on those without)
    or ``"auto"`` (bf16 for batches of at least :data:`.devices.AUTO_BF16_MIN_BATCH` frustums on a CPU
    with AMX, else fp32); onnxruntime runs fp32, with ``"int8"`` the box and shape
    PointNets' wide layers in int8, with ``"auto"`` those of some passes
    (:func:`.onnx_quantize.quantized_passes`). Torch runs ``"int8"`` as fp32.
    ``trace`` (torch, CPU): frozen TorchScript graphs (:mod:`.traced`); False = eager (and
    ``backend="auto"`` then means torch). ``points``: points per frustum to run at (0: the
    count the network was trained with, :attr:`ModelConfig.num_points`); warm-up and tracing
    use it, so every frustum given to this predictor should have that many.
    """

    def __init__(
        self,
        weights: str | Path | None = None,
        device: str | torch.device = "cpu",
        num_threads: int | None = None,
        workers: int = 1,
        min_chunk: int = 1,
        precision: str = "fp32",
        trace: bool = True,
        backend: str = "auto",
        points: int = 0,
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        if int(points) < 0:
            raise ValueError(f"points must be >= 0 (0: the network's own count), got {points}")
        self.precision = precision
        self.num_threads = num_threads
        self._points = int(points)
        self.backend = resolve_backend(backend, precision, trace, str(device))
        self._trace = bool(trace)
        self.workers = max(1, int(workers))
        self.min_chunk = max(1, int(min_chunk))
        self._pool: ThreadPoolExecutor | None = None
        self._model: Any = None  # the torch network, loaded lazily under onnxruntime
        self._ort: OrtFrustumForward | None = None
        self.meta: dict = {}
        if weights is None:
            p = default_weights_path()
            if p.is_file():
                weights = p
            else:
                warnings.warn(f"no packaged weights at {p}; using a randomly initialised network", stacklevel=2)
        self.weights_path = None if weights is None else Path(weights)
        if self.backend == "onnxruntime":
            try:
                self._init_onnxruntime(device)
                return
            except Exception as e:  # noqa: BLE001 - any export / session failure: torch serves
                warnings.warn(f"onnxruntime backend unavailable ({type(e).__name__}: {e}); using torch", stacklevel=2)
                self.backend, self._ort = "torch", None
        self._init_torch(device)

    def _load_model(self) -> tuple[Any, dict]:
        """(fused eval-mode network, meta) of ``weights_path`` (random when None); imports torch."""
        import torch

        from .io import load_weights
        from .network import FrustumShapeNet

        if self.weights_path is None:
            torch.manual_seed(0)
            model, meta = FrustumShapeNet(ModelConfig()).eval(), {}
        else:
            model, meta = load_weights(self.weights_path, "cpu")
        return model.fuse_batchnorm(), meta  # inference only: BatchNorm folded into the linear layers

    def _init_torch(self, device: Any) -> None:
        import torch

        if self.precision == "int8":  # int8 graphs are onnxruntime's (resolve_backend warned)
            self.precision = "fp32"
        from .traced import TracedForward

        if self.num_threads is not None:
            torch.set_num_threads(int(self.num_threads))
        self.device = resolve_device(device)
        if self.device.type != "cpu":
            self.workers = 1
        self.bf16_min_batch = bf16_min_batch(self.precision, self.device)
        if self._model is None:
            self._model, self.meta = self._load_model()
        self._model = self._model.to(self.device)
        self._forward = TracedForward(self._model, enabled=self._trace and self.device.type == "cpu")

    def _init_onnxruntime(self, device: Any) -> None:
        from .onnx_backend import OrtFrustumForward
        from .onnx_export import frustum_graphs

        folder, info, self._model = frustum_graphs(self.weights_path, self._load_model)
        self.meta = dict(info.get("meta") or {})
        if self.meta.get("tasks") is None:
            self.meta.pop("tasks", None)
        self._config = ModelConfig.from_dict(info["model_config"])
        self.device = "cpu" if str(device) == "cpu" else str(device)
        self.bf16_min_batch = None
        self.graph_folder = folder
        int8 = quantized_graphs(self.precision)
        if int8:
            try:
                int8_graphs(folder, int8)
            except ImportError as e:  # the quantiser needs the onnx package; the float32 graphs do not
                warnings.warn(f"precision {self.precision} cannot build its int8 graphs ({e}); running float32",
                              stacklevel=3)
                self.precision, int8 = "fp32", ()
        self._ort = OrtFrustumForward(folder, int(self.num_threads or 1), self.device, int8=int8,
                                      fp32_head=quantized_passes(self.precision) != frozenset(HEAD_PASSES))

    @property
    def int8_graphs(self) -> tuple[str, ...]:
        """The onnxruntime graphs this predictor runs in int8 (:func:`.onnx_quantize.quantized_graphs`)."""
        return quantized_graphs(self.precision) if self.backend == "onnxruntime" else ()

    def load_weights(self, path: str | Path) -> None:
        """Load another weights file (torch backend: in place; onnxruntime: its graphs)."""
        self.weights_path, self._model = Path(path), None
        if self.backend == "onnxruntime":
            self._init_onnxruntime(self.device)
        else:
            self._init_torch(self.device)

    @property
    def model(self) -> Any:
        """The (BatchNorm-folded) torch network; loaded on first use under onnxruntime."""
        if self._model is None:
            self._model, self.meta = self._load_model()
        return self._model

    def warm_up(self, max_batch: int = 1) -> None:
        """Build now, on dummy frustums, what a frame may need (torch: trace the first pass
        and the feature-reusing second pass, in each precision this predictor uses, with
        caches of either dtype), so that no camera frame pays for it; then run both passes
        once for every batch of 1 to ``max_batch`` frustums (oneDNN and onnxruntime prepare
        kernels per shape)."""
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
                cache = (_repeat_first(glob, b), _repeat_first(local, b))
                self.forward_arrays(np.zeros((b, n, 6), np.float32), np.eye(b, nc, dtype=np.float32), cache)
        dummy = Frustum(np.zeros((n, 6), np.float32), np.arange(n), 0, 0.0, np.eye(3))
        for b in range(1, int(max_batch) + 1):
            first = self.predict([dummy] * b, [None] * b, keep_features=True)
            self.predict([dummy] * b, [0] * b, seg_features=[p.seg_features for p in first])

    @property
    def config(self) -> ModelConfig:
        """The network's configuration (of the torch model, or read with the onnxruntime graphs)."""
        if self._ort is not None:
            return self._config
        assert self._model is not None, "torch backend without a network"
        return self._model.config

    @property
    def num_points(self) -> int:
        """Points per frustum to extract: ``points`` where given, else the count the network
        was trained with."""
        return self._points or int(self.config.num_points)

    @property
    def has_class_head(self) -> bool:
        """Whether the weights were trained with the class head (task ``cls``; older weights: assumed)."""
        tasks = self.meta.get("tasks")
        return tasks is None or "cls" in tasks

    # --------------------------------------------------------------------------
    def forward_arrays(
        self,
        points: np.ndarray,
        one_hot: np.ndarray,
        seg_cache: tuple[Any, Any] | None = None,
        keep_features: bool = False,
        shapes: bool = True,
        fp32: bool = False,
    ) -> dict[str, np.ndarray]:
        """Raw batched forward on (B,N,6) points / (B,C) one-hot; decoded frame-F arrays.

        ``seg_cache``: the ``seg_glob`` / ``seg_local`` of an earlier call on the same points
        (the segmentation PointNet is skipped); ``keep_features`` adds them to the result
        (numpy arrays under onnxruntime, torch tensors under torch). ``shapes=False`` lets
        onnxruntime skip the shape branch (the primitives are then meaningless; torch
        computes them anyway). ``fp32``: onnxruntime runs the shape head in float32 whatever
        the precision's int8 graphs.
        """
        if self._ort is not None:
            out = self._ort(points, one_hot, seg_cache, shapes, fp32)
            if not keep_features:
                out.pop("seg_glob"), out.pop("seg_local")
            return out
        return self._forward_torch(points, one_hot, seg_cache, keep_features)

    def _forward_torch(self, points, one_hot, seg_cache, keep_features) -> dict[str, Any]:
        import torch

        with torch.inference_mode():
            pts = torch.as_tensor(np.asarray(points, np.float32), device=self.device)
            oh = torch.as_tensor(np.asarray(one_hot, np.float32), device=self.device)
            if seg_cache is not None:
                seg_cache = tuple(torch.as_tensor(c, device=self.device) for c in seg_cache)
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
        seg_features: Sequence[tuple[Any, Any] | None] | None = None,
        shapes: bool = True,
        second: bool = False,
    ) -> list[FrustumPrediction]:
        """Predictions for ``frustums`` (class ids: index into CLASSES, or None = unknown).

        ``mirror``: test-time augmentation; each frustum also runs mirrored (x -> -x in frame F,
        a symmetry the training augments with) in the same batch, and the two predictions are
        averaged (:func:`merge_mirrored`). Twice the network work.
        ``keep_features`` (no mirror): each prediction keeps its frustum's segmentation
        features (``FrustumPrediction.seg_features``); ``seg_features``: such features of an
        earlier pass over the same frustums, one per frustum (used where a whole
        same-size group has them, without mirror: that group skips the segmentation PointNet).
        ``shapes=False``: no primitives (empty lists; the shape branch is skipped where the
        runtime can), for a pass whose primitives a later pass replaces. ``second``: the
        class-given second pass (:meth:`refine`), for the precision's choice of int8 passes.
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
        int8 = quantized_passes(self.precision) if self._ort is not None else frozenset()
        for _, idx in groups.items():
            role = "second" if second else "given" if all(class_ids[i] is not None for i in idx) else "agnostic"
            fp32 = role not in int8
            pts = np.stack([frustums[i].points[:, :6] for i in idx]).astype(np.float32)
            oh = np.zeros((len(idx), nc), np.float32)
            for j, i in enumerate(idx):
                if class_ids[i] is not None:
                    oh[j, int(class_ids[i])] = 1.0
            cache = None
            if seg_features is not None and not mirror and all(seg_features[i] is not None for i in idx):
                cache = (_stack([seg_features[i][0] for i in idx]), _stack([seg_features[i][1] for i in idx]))  # type: ignore[index]
            if mirror:
                flipped = pts.copy()
                flipped[..., 0] *= -1.0
                arr = merge_mirrored(self._forward_parallel(np.concatenate([pts, flipped]), np.concatenate([oh, oh]),
                                                            shapes=shapes, fp32=fp32))
            else:
                arr = self._forward_parallel(pts, oh, cache, keep, shapes, fp32)
            for j, p in enumerate(self._decode([frustums[i] for i in idx], [class_ids[i] for i in idx], arr, shapes)):
                results[idx[j]] = p
                if keep:
                    p.seg_features = (arr["seg_glob"][j], arr["seg_local"][j])
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
            second=True,
        )
        for i, q in zip(idx, second):
            p = first[i]
            out[i] = replace(q, class_name=p.class_name, class_probs=p.class_probs, score=refined_score(p.score, q.objectness))
        return out

    def _forward_parallel(
        self,
        pts: np.ndarray,
        oh: np.ndarray,
        seg_cache: tuple[Any, Any] | None = None,
        keep_features: bool = False,
        shapes: bool = True,
        fp32: bool = False,
    ) -> dict[str, Any]:
        """:meth:`forward_arrays`, split over ``self.workers`` threads for large batches."""
        n = pts.shape[0]
        k = min(self.workers, n // self.min_chunk)
        if k <= 1:
            return self.forward_arrays(pts, oh, seg_cache, keep_features, shapes, fp32)
        pool = self._pool
        if pool is None:
            from concurrent.futures import ThreadPoolExecutor

            pool = self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="frustum-net")
        bounds = np.linspace(0, n, k + 1).round().astype(int)
        futs = [
            pool.submit(
                self.forward_arrays,
                pts[a:b],
                oh[a:b],
                None if seg_cache is None else (seg_cache[0][a:b], seg_cache[1][a:b]),
                keep_features,
                shapes,
                fp32,
            )
            for a, b in zip(bounds[:-1], bounds[1:])
        ]
        parts = [f.result() for f in futs]
        return {key: _concat([p[key] for p in parts]) for key in parts[0]}

    def _decode(self, frs: Sequence[Frustum], cids: Sequence[int | None], arr: dict[str, np.ndarray],
                shapes: bool = True) -> list[FrustumPrediction]:
        """One :class:`FrustumPrediction` per row of ``arr`` (frame F -> camera), the
        rotations, centres and primitive transforms computed for the whole batch at once
        (``shapes=False``: no primitives)."""
        nc = self.config.num_classes
        B = len(frs)
        probs = np.asarray(arr["probs"][:B], np.float64)
        objectness = 1.0 - probs[:, nc]
        best = np.argmax(probs[:, :nc], axis=1)
        given = np.array([c is not None for c in cids])
        cls = np.where(given, [int(c) if c is not None else 0 for c in cids], best)
        score = np.where(given, objectness, probs[np.arange(B), best])
        if not self.has_class_head:
            score = np.asarray(arr["fg_score"][:B], np.float64)
        valid = np.array([int(f.valid) for f in frs])
        score = np.clip(np.where(valid > 0, score, 0.0), 0.0, 1.0)
        phi = np.array([float(f.phi) for f in frs])
        R_cf = np.stack([f.R_cu for f in frs]).astype(np.float64) @ rot_z(-phi).reshape(B, 3, 3)
        center_F = np.asarray(arr["center"][:B], np.float64)
        heading_F = np.asarray(arr["heading"][:B], np.float64)
        size = np.asarray(arr["size"][:B], np.float64)
        R_box = R_cf @ rot_z(heading_F).reshape(B, 3, 3)
        center = np.einsum("bij,bj->bi", R_cf, center_F)
        pc = np.asarray(arr["prim_center"][:B], np.float64)
        ps = np.asarray(arr["prim_size"][:B], np.float64)
        pr = np.asarray(arr["prim_rotation"][:B], np.float64)
        # primitives: prune low-volume ones (keep at least the largest)
        vol = np.prod(ps, axis=2)
        keep = vol >= self.config.prune_volume_frac * np.prod(size, axis=1, keepdims=True)
        keep[np.arange(B), np.argmax(vol, axis=1)] |= ~keep.any(1)
        keep &= bool(shapes)
        cam_c = np.einsum("bij,bmj->bmi", R_box, pc) + center[:, None, :]
        cam_r = np.einsum("bij,bmjk->bmik", R_box, pr)
        heading_U = wrap_angle(heading_F - phi)
        seg_prob = np.asarray(arr["seg_prob"][:B], np.float32)
        out = []
        for j in range(B):
            ms = np.nonzero(keep[j])[0]
            out.append(FrustumPrediction(
                class_name=CLASSES[int(cls[j])],
                class_probs=probs[j],
                score=float(score[j]),
                center=center[j],
                size=size[j],
                rotation=R_box[j],
                heading_U=float(heading_U[j]),
                primitives=[Cuboid(cam_c[j, m], ps[j, m], cam_r[j, m]) for m in ms],
                seg_prob=seg_prob[j],
                num_points_valid=int(valid[j]),
                objectness=float(objectness[j]),
                center_F=center_F[j],
                heading_F=float(heading_F[j]),
                primitives_canonical=[Cuboid(pc[j, m], ps[j, m], pr[j, m]) for m in ms],
            ))
        return out

