"""Inference of the proposal classifier: ONNX Runtime or PyTorch (torch imported only for the
latter, or to export a graph that is not cached yet)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .classifier_inputs import GLOBAL_FEATURES, POINT_CHANNELS, ClassifierConfig, subsample_points
from .onnx_backend import OrtClassifier, resolve_backend


class ClassifierPredictor:
    """Inference with a loaded :class:`~shape_detector.model.classifier.ProposalClassifier`,
    as :class:`~shape_detector.model.predictor.FrustumPredictor` runs the network.

    ``backend`` (see :mod:`.onnx_backend`): ``"auto"`` (default: onnxruntime where
    installed), ``"onnxruntime"`` (the graph is exported once per model state and cached,
    :mod:`.onnx_export`) or ``"torch"``: BatchNorm folded, frozen TorchScript graphs
    (``trace``) and bfloat16 for batches from the predictor's threshold on under
    ``precision`` (``"auto"``: 4 or more candidates on a CPU with AMX). Same
    :meth:`probabilities` as the classifier; ``model`` is folded in place (eval mode; it can
    no longer be trained). ``num_threads``: onnxruntime intra-op threads.
    :meth:`from_file` starts from a weights file and skips torch when its graph is cached.
    """

    def __init__(self, model: Any, precision: str = "fp32", trace: bool = True, backend: str = "auto",
                 num_threads: int = 1) -> None:
        precision = _no_int8(precision)
        self.precision = precision
        self.backend = resolve_backend(backend, precision, trace)
        self.model = model.eval().fuse_batchnorm() if model is not None else None
        self._ort = None
        self._config: ClassifierConfig | None = None
        self.bf16_min_batch = None
        if self.model is not None and self.backend == "onnxruntime":
            try:
                from .onnx_export import classifier_graph

                self._ort = OrtClassifier(classifier_graph(self.model), num_threads)
            except Exception as e:  # noqa: BLE001 - any export / session failure: torch serves
                warnings.warn(f"onnxruntime classifier unavailable ({type(e).__name__}: {e}); using torch", stacklevel=2)
                self.backend = "torch"
        if self.model is not None and self._ort is None:
            self._init_torch(trace)

    def _init_torch(self, trace: bool) -> None:
        from .classifier import _Calibrated
        from .devices import bf16_min_batch
        from .traced import TracedModule

        self.backend = "torch"
        self.bf16_min_batch = bf16_min_batch(self.precision, "cpu")
        self._run = TracedModule(_Calibrated(self.model), enabled=trace)

    @classmethod
    def from_file(cls, path: str | Path, precision: str = "fp32", trace: bool = True, backend: str = "auto",
                  num_threads: int = 1) -> ClassifierPredictor:
        """A predictor for a classifier weights file. Under onnxruntime, the graph cached for
        the file's sha256 is used without importing torch; missing, it is exported first."""
        from ..digests import sha256_file
        from .onnx_export import GRAPH_FILES, cache_dir, ensure_graphs, export_classifier_graph

        precision = _no_int8(precision)
        if resolve_backend(backend, precision, trace) == "onnxruntime":
            try:
                folder = cache_dir("classifier-file", sha256_file(path))

                def export() -> None:
                    from .classifier import load_classifier

                    export_classifier_graph(load_classifier(path)[0].eval().fuse_batchnorm(), folder)

                info = ensure_graphs(folder, ("classifier",), export)
                if info is None:
                    raise RuntimeError(f"export to {folder} left no usable classifier graph")
                self = cls(None, precision, trace, backend, num_threads)
                self._config = ClassifierConfig.from_dict(info["classifier_config"])
                self._ort = OrtClassifier(folder / GRAPH_FILES["classifier"], num_threads)
                return self
            except Exception as e:  # noqa: BLE001 - as in __init__
                warnings.warn(f"onnxruntime classifier unavailable ({type(e).__name__}: {e}); using torch", stacklevel=2)
        from .classifier import load_classifier

        return cls(load_classifier(path)[0], precision, trace, "torch")

    @property
    def config(self) -> ClassifierConfig:
        """The classifier's configuration (of the torch model, or read with the onnxruntime graph)."""
        if self.model is not None:
            return self.model.config
        assert self._config is not None, "classifier without a model or a cached graph's config"
        return self._config

    def warm_up(self, max_batch: int = 1) -> None:
        """Trace the graphs and build the kernels for every batch of 1 to ``max_batch``
        candidates now (see :meth:`FrustumPredictor.warm_up
        <shape_detector.model.predictor.FrustumPredictor.warm_up>`)."""
        n, g = self.config.num_points, len(GLOBAL_FEATURES)
        for b in range(1, max(1, int(max_batch)) + 1):
            self.probabilities(np.zeros((b, n, POINT_CHANNELS), np.float32), np.zeros((b, g), np.float32))

    def probabilities(self, points: np.ndarray, globals_: np.ndarray) -> np.ndarray:
        """Calibrated probabilities (B, num_classes + 1) float64, background last, of
        :func:`~.classifier_inputs.candidate_inputs`' arrays (``config.num_points`` evenly
        spaced points used)."""
        if len(points) == 0:
            return np.zeros((0, self.config.num_classes + 1), np.float64)
        pts = subsample_points(points, self.config.num_points)
        g = np.asarray(globals_, np.float32)
        if self._ort is not None:
            return self._ort(pts, g).astype(np.float64)
        import torch

        bf16 = self.bf16_min_batch is not None and len(pts) >= self.bf16_min_batch
        with torch.inference_mode():
            return self._run(torch.as_tensor(pts), torch.as_tensor(g), bf16=bf16)[0].double().numpy()


def _no_int8(precision: str) -> str:
    """The classifier's precision for the detector's: it has no int8 graph (it is small), so
    ``"int8"`` runs it in float32."""
    return "fp32" if precision == "int8" else precision
