"""ONNX Runtime inference of the exported graphs (:mod:`.onnx_export`), and the backend choice.

``backend``: ``"onnxruntime"`` runs the graphs in ONNX Runtime (CPU execution provider;
TensorRT / CUDA providers first where installed and the device is not ``"cpu"``),
``"torch"`` runs the PyTorch module (TorchScript graphs or eager), ``"auto"`` picks
onnxruntime when it imports, else torch with one warning. ``"auto"`` also picks torch for
what only torch does: ``precision="bf16"`` and the eager forward (``trace=False``, which
module hooks and debuggers need). ``precision="int8"`` runs only in onnxruntime
(:mod:`.onnx_quantize`): ``"torch"`` refuses it, ``"auto"`` without onnxruntime warns and
runs float32 in torch. The environment variable ``SHAPE_DETECTOR_BACKEND``
(``onnxruntime`` / ``torch``) overrides ``"auto"`` (for A/B runs of whole programs).

Nothing here imports torch.
"""

from __future__ import annotations

import importlib
import os
import threading
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .onnx_export import GRAPH_FILES, HEAD_OUTPUTS

BACKENDS = ("auto", "onnxruntime", "torch")
_warned_missing = False
_warn_lock = threading.Lock()


def ort_available() -> bool:
    """Whether ``onnxruntime`` imports."""
    try:
        importlib.import_module("onnxruntime")
    except ImportError:
        return False
    return True


def resolve_backend(backend: str = "auto", precision: str = "fp32", trace: bool = True, device: str = "cpu") -> str:
    """``"onnxruntime"`` or ``"torch"`` for a ``backend`` setting (see the module docstring).
    ``"onnxruntime"`` asked for but not installed raises ImportError; ``"auto"`` without it
    warns once per process and gives ``"torch"``. ``"auto"`` with a GPU ``device`` (not
    ``"cpu"``) gives ``"torch"`` when this onnxruntime has no GPU execution provider but
    torch sees a GPU: the device asked for, not onnxruntime on the CPU."""
    global _warned_missing
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        env = os.environ.get("SHAPE_DETECTOR_BACKEND", "").strip()
        if env in ("onnxruntime", "torch"):
            backend = env
    if backend == "torch":
        if precision == "int8":
            raise ValueError("precision 'int8' runs in onnxruntime: use backend 'onnxruntime' or 'auto'")
        return "torch"
    if backend == "onnxruntime":
        if not ort_available():
            raise ImportError("backend='onnxruntime' needs the onnxruntime package (pip install onnxruntime)")
        return "onnxruntime"
    if precision == "bf16" or (not trace and precision != "int8"):
        return "torch"
    if ort_available():
        if str(device) != "cpu" and not gpu_providers() and _torch_sees_gpu(device):
            return "torch"
        return "onnxruntime"
    with _warn_lock:
        if not _warned_missing:
            _warned_missing = True
            warnings.warn("onnxruntime is not installed: running the networks in PyTorch (slower on most CPUs"
                          + ("; precision int8 runs as fp32 there)" if precision == "int8" else ")"), stacklevel=3)
    return "torch"


def gpu_providers() -> list[str]:
    """The GPU execution providers (TensorRT, CUDA) this onnxruntime has, best first."""
    import onnxruntime as ort

    have = set(ort.get_available_providers())
    return [p for p in ("TensorrtExecutionProvider", "CUDAExecutionProvider") if p in have]


def _torch_sees_gpu(device: str) -> bool:
    """Whether torch imports and ``device`` (``"auto"``, ``"cuda"``, ``"cuda:N"``, ...) resolves to a GPU."""
    try:
        from .devices import resolve_device

        return resolve_device(device).type != "cpu"
    except Exception:  # noqa: BLE001 - no torch, or a device torch does not know: onnxruntime serves
        return False


def providers_for(device: str) -> list[str]:
    """Execution providers for ``device`` (``"cpu"``, ``"cuda"``, ``"auto"``): CPU only for
    ``"cpu"``, else TensorRT / CUDA where this onnxruntime has them, then CPU."""
    if str(device) == "cpu":
        return ["CPUExecutionProvider"]
    return gpu_providers() + ["CPUExecutionProvider"]


def make_session(path: str | Path, threads: int = 1, device: str = "cpu", spinning: bool = False) -> Any:
    """An ``onnxruntime.InferenceSession`` for ``path``: ``threads`` intra-op threads, one
    inter-op thread, all graph optimisations; ``spinning`` False (default) lets idle pool
    threads sleep instead of spinning, which on a shared 2-core machine would take the core
    the other pipeline stage needs."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = max(1, int(threads))
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    return ort.InferenceSession(str(path), so, providers=providers_for(device))


class OrtFrustumForward:
    """The frustum network's inference forward in onnxruntime: ``forward(points, one_hot,
    seg_cache, shapes)`` -> the dict of :meth:`FrustumPredictor.forward_arrays
    <shape_detector.model.predictor.FrustumPredictor.forward_arrays>` (numpy; ``seg_glob`` /
    ``seg_local`` included; ``shapes=False``: without the shape branch, primitives zeros).
    ``folder`` holds ``frustum_seg.onnx`` / ``frustum_head.onnx`` / ``frustum_box.onnx``
    (``int8``: the names of those to take in their ``.int8.onnx`` versions instead;
    ``fp32_head``: keep the float32 head too, for the passes that ask for it).
    Sessions are thread-safe: chunks of a batch may run on several Python threads (the GIL
    is released while a graph runs)."""

    def __init__(self, folder: str | Path, threads: int = 1, device: str = "cpu", int8: tuple[str, ...] = (),
                 fp32_head: bool = False) -> None:
        folder = Path(folder)
        files = dict(GRAPH_FILES)
        if int8:  # these graphs' int8 versions (built by .onnx_quantize.int8_graphs)
            from .onnx_quantize import int8_file

            files.update({n: int8_file(n) for n in int8})
        self.seg = make_session(folder / files["frustum_seg"], threads, device)
        self.head = make_session(folder / files["frustum_head"], threads, device)
        self.box = make_session(folder / files["frustum_box"], threads, device)
        self.head_fp32 = (make_session(folder / GRAPH_FILES["frustum_head"], threads, device)
                          if fp32_head and "frustum_head" in int8 else self.head)

    def __call__(
        self,
        points: np.ndarray,
        one_hot: np.ndarray,
        seg_cache: tuple[np.ndarray, np.ndarray] | None = None,
        shapes: bool = True,
        fp32: bool = False,
    ) -> dict[str, np.ndarray]:
        """Run the graphs on ``points`` (B, N, C) float32 (frame F, m) and ``one_hot`` (B, num_classes);
        ``seg_cache``: the ``(seg_glob, seg_local)`` of an earlier pass on the same points;
        ``fp32``: the head in float32 (where it was kept)."""
        pts = np.ascontiguousarray(points, np.float32)
        if seg_cache is None:
            glob, local = self.seg.run(None, {"points": pts})
        else:
            glob, local = (np.ascontiguousarray(_numpy(t), np.float32) for t in seg_cache)
        graph = (self.head_fp32 if fp32 else self.head) if shapes else self.box
        outs = graph.run(None, {"points": pts, "one_hot": np.ascontiguousarray(one_hot, np.float32),
                                "seg_glob": glob, "seg_local": local})
        res = dict(zip(HEAD_OUTPUTS, outs))
        res["seg_glob"], res["seg_local"] = glob, local
        return res


class OrtClassifier:
    """The proposal classifier's calibrated probabilities in onnxruntime: ``(points (B,N,7),
    globals (B,G))`` float32 -> ``(B, C+1)``."""

    def __init__(self, path: str | Path, threads: int = 1, device: str = "cpu") -> None:
        self.session = make_session(path, threads, device)

    def __call__(self, points: np.ndarray, globals_: np.ndarray) -> np.ndarray:
        """Probabilities (B, C+1), background last, of candidates ``points`` (B, N, 7) and ``globals_`` (B, G)."""
        return self.session.run(None, {"points": np.ascontiguousarray(points, np.float32),
                                       "globals": np.ascontiguousarray(globals_, np.float32)})[0]


def _numpy(t: Any) -> np.ndarray:
    """A numpy view of an array or a (CPU) torch tensor, without importing torch."""
    if isinstance(t, np.ndarray):
        return t
    return t.detach().cpu().numpy() if hasattr(t, "detach") else np.asarray(t)
