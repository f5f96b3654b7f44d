"""ONNX graphs of the inference forwards, checked against PyTorch and cached by weights digest.

Four graphs, each with a dynamic batch axis (and a dynamic point axis where it has one):

* ``frustum_seg``: ``points (B,N,6)`` -> ``seg_glob (B,G)``, ``seg_local (B,N,H)``: the
  class-independent segmentation features of :meth:`FrustumShapeNet.seg_features
  <shape_detector.model.network.FrustumShapeNet.seg_features>`;
* ``frustum_head``: ``points, one_hot (B,C), seg_glob, seg_local`` -> the decoded outputs of
  :func:`~shape_detector.model.traced.inference_outputs` (:data:`HEAD_OUTPUTS`, frame F).
  A first pass runs both graphs; the class-given second pass reuses the first pass's
  features and runs only this one;
* ``frustum_box``: ``frustum_head`` without the shape branch (same inputs and outputs, the
  primitives zeros): a first pass whose primitives the second pass replaces;
* ``classifier``: ``points (B,N,7), globals (B,G)`` -> calibrated ``probs (B,C+1)`` of the
  proposal classifier.

Export needs torch (and the ``onnx`` package); running the graphs needs only onnxruntime.
Every export is run once through onnxruntime on random inputs of two batch sizes and
compared with the PyTorch module (:data:`CHECK_ATOL`); a graph that disagrees is not used.
Cached graphs live under ``$SHAPE_DETECTOR_CACHE``, else ``$XDG_CACHE_HOME/shape_detector``,
else ``~/.cache/shape_detector`` (a temp dir when none is writable), in a folder named by
the sha256 of the weights file (or of the module's state when there is no file) and
:data:`EXPORT_VERSION`, with a ``graphs.json`` describing inputs, outputs and the model
config (which lets a predictor start from the cache without importing torch). Processes that
start together on a cold cache (two nodes, detector worker processes) take turns on a folder
(:func:`cache_lock`): one exports, the others then find its graphs.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..digests import sha256_file

#: bump when the graphs' inputs / outputs or their semantics change (invalidates caches)
EXPORT_VERSION = 1
OPSET = 17
#: absolute tolerance of the export check (float32 reordering noise is ~1e-6)
CHECK_ATOL = 1e-4
#: ``frustum_head``'s outputs, in order (:data:`~shape_detector.model.traced.OUTPUT_KEYS`
#: without the segmentation features)
HEAD_OUTPUTS = (
    "probs", "seg_prob", "center", "heading", "heading_conf", "size", "cluster", "fg_score",
    "prim_center", "prim_size", "prim_rotation",
)
GRAPH_FILES = {"frustum_seg": "frustum_seg.onnx", "frustum_head": "frustum_head.onnx", "frustum_box": "frustum_box.onnx",
               "classifier": "classifier.onnx"}
#: the frustum network's graphs, all needed for a usable export
FRUSTUM_GRAPHS = ("frustum_seg", "frustum_head", "frustum_box")
META_FILE = "graphs.json"


def cache_root() -> Path:
    """A writable folder for cached graphs (created): ``$SHAPE_DETECTOR_CACHE``, else
    ``$XDG_CACHE_HOME/shape_detector``, else ``~/.cache/shape_detector``, else a temp dir."""
    candidates = []
    if os.environ.get("SHAPE_DETECTOR_CACHE"):
        candidates.append(Path(os.environ["SHAPE_DETECTOR_CACHE"]))
    xdg = os.environ.get("XDG_CACHE_HOME")
    candidates.append((Path(xdg) if xdg else Path.home() / ".cache") / "shape_detector")
    candidates.append(Path(tempfile.gettempdir()) / f"shape_detector-{os.getuid() if hasattr(os, 'getuid') else 0}")
    for c in candidates:
        try:
            c.mkdir(parents=True, exist_ok=True)
            if os.access(c, os.W_OK):
                return c
        except OSError:
            continue
    return Path(tempfile.mkdtemp(prefix="shape_detector-"))


def module_digest(module: Any) -> str:
    """sha256 (hex) of a torch module's state (names, dtypes, shapes, values)."""
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        arr = t.detach().cpu().contiguous().numpy()
        h.update(f"{name}:{arr.dtype}:{arr.shape}".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def cache_dir(kind: str, digest: str) -> Path:
    """The cache folder of ``kind`` (``"frustum"`` / ``"classifier"``) graphs for weights of
    sha256 ``digest``."""
    return cache_root() / f"{kind}-v{EXPORT_VERSION}-{digest[:32]}"


@contextmanager
def cache_lock(folder: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on the cache ``folder`` (created) across processes while writing
    into it: the exporter and the quantiser write and delete files beside the graphs, which
    two processes doing the same at once would take from each other. POSIX ``flock``; a
    no-op where ``fcntl`` does not exist. Not re-entrant: never nest two on one folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # not POSIX (Windows): unlocked, as before
        yield
        return
    with open(folder / ".lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def read_meta(folder: str | Path) -> dict[str, Any] | None:
    """``graphs.json`` of an export folder, None when missing or unreadable."""
    try:
        return json.loads((Path(folder) / META_FILE).read_text())
    except (OSError, ValueError):
        return None


def _write_meta(folder: Path, meta: dict[str, Any]) -> None:
    old = read_meta(folder) or {}
    graphs = {**old.get("graphs", {}), **meta.pop("graphs", {})}
    merged = {**old, **meta, "graphs": graphs, "export_version": EXPORT_VERSION, "opset": OPSET}
    tmp = folder / f"{META_FILE}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(merged, indent=2, default=str))
    os.replace(tmp, folder / META_FILE)


# --------------------------------------------------------------------------- torch side
def _wrappers():
    """The export wrappers (defined lazily: torch is only imported to export)."""
    import torch
    from torch import nn

    from .traced import inference_outputs

    class SegGraph(nn.Module):
        def __init__(self, model: nn.Module) -> None:
            super().__init__()
            self.model = model

        def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return self.model.seg_features(points)

    class HeadGraph(nn.Module):
        def __init__(self, model: nn.Module, with_shape: bool = True) -> None:
            super().__init__()
            self.model = model
            self.with_shape = with_shape

        def forward(self, points, one_hot, seg_glob, seg_local) -> tuple[torch.Tensor, ...]:
            out = inference_outputs(self.model, points, one_hot, (seg_glob, seg_local), with_shape=self.with_shape)
            return out[: len(HEAD_OUTPUTS)]

    class ClassifierGraph(nn.Module):
        def __init__(self, model: nn.Module) -> None:
            super().__init__()
            self.model = model

        def forward(self, points, globals_) -> tuple[torch.Tensor]:
            return self.model.calibrated(points, globals_)

    return SegGraph, HeadGraph, ClassifierGraph


def _export(module: Any, args: tuple, path: Path, inputs: dict[str, dict[int, str]], outputs: dict[str, dict[int, str]]) -> None:
    import torch

    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarnings of shape-dependent Python and the exporter's notices
        torch.onnx.export(
            module.eval(), args, str(tmp), input_names=list(inputs), output_names=list(outputs),
            dynamic_axes={**inputs, **outputs}, opset_version=OPSET, dynamo=False,
        )
    os.replace(tmp, path)


def _check(path: Path, module: Any, make_inputs, names: list[str], atol: float) -> float:
    """Largest |onnxruntime - torch| over the outputs, for batches of 1 and 5 (raises when
    over ``atol``)."""
    import onnxruntime as ort
    import torch

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for b in (1, 5):
        args = make_inputs(b)
        with torch.inference_mode():
            want = module(*args)
        want = want if isinstance(want, tuple) else (want,)
        got = sess.run(None, {n: a.numpy() for n, a in zip(names, args)})
        for w, g in zip(want, got):
            if tuple(w.shape) != g.shape:
                raise RuntimeError(f"{path.name}: output shape {g.shape}, torch {tuple(w.shape)}")
            worst = max(worst, float(np.abs(w.float().numpy() - g.astype(np.float32)).max(initial=0.0)))
    if worst > atol:
        raise RuntimeError(f"{path.name}: onnxruntime differs from torch by {worst:.3g} (> {atol:g})")
    return worst


def export_frustum_graphs(model: Any, folder: str | Path, meta: dict[str, Any] | None = None) -> dict[str, Path]:
    """Export (and check) ``frustum_seg``, ``frustum_head`` and ``frustum_box`` of an eval-mode
    :class:`~shape_detector.model.network.FrustumShapeNet` (BatchNorm folded or not) into
    ``folder``; ``graphs.json`` gets their inputs / outputs, the model config and ``meta``
    (e.g. the weights' ``tasks``). Returns the graph paths."""
    import torch

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    SegGraph, HeadGraph, _ = _wrappers()
    cfg = model.config
    n, nc = int(cfg.num_points), int(cfg.num_classes)
    seg, head, box = SegGraph(model).eval(), HeadGraph(model).eval(), HeadGraph(model, with_shape=False).eval()

    def points(b: int, seed: int = 0) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed + b)
        p = torch.randn(b, n, 6, generator=g) * 0.5
        p[..., 2] += 3.0
        p[..., 3:] = torch.rand(b, n, 3, generator=g)
        return p

    def one_hot(b: int) -> torch.Tensor:
        oh = torch.zeros(b, nc)
        oh[: b // 2, 1] = 1.0  # half class-given, half class-agnostic
        return oh

    def head_inputs(b: int) -> tuple:
        p = points(b)
        with torch.inference_mode():
            glob, local = seg(p)
        return p, one_hot(b), glob.clone(), local.clone()

    batch = {0: "batch", 1: "points"}
    paths = {k: folder / GRAPH_FILES[k] for k in FRUSTUM_GRAPHS}
    _export(seg, (points(2),), paths["frustum_seg"], {"points": batch},
            {"seg_glob": {0: "batch"}, "seg_local": batch})
    out_axes = {k: ({0: "batch", 1: "points"} if k == "seg_prob" else {0: "batch"}) for k in HEAD_OUTPUTS}
    in_names = ["points", "one_hot", "seg_glob", "seg_local"]
    head_axes = {"points": batch, "one_hot": {0: "batch"}, "seg_glob": {0: "batch"}, "seg_local": batch}
    _export(head, head_inputs(2), paths["frustum_head"], head_axes, out_axes)
    _export(box, head_inputs(2), paths["frustum_box"], head_axes, out_axes)
    err_seg = _check(paths["frustum_seg"], seg, lambda b: (points(b, 7),), ["points"], CHECK_ATOL)
    err_head = _check(paths["frustum_head"], head, head_inputs, in_names, CHECK_ATOL)
    err_box = _check(paths["frustum_box"], box, head_inputs, in_names, CHECK_ATOL)
    _write_meta(folder, {
        "model_config": cfg.to_dict(),
        "meta": dict(meta or {}),
        "graphs": {
            "frustum_seg": {"file": GRAPH_FILES["frustum_seg"], "inputs": {"points": ["B", "N", 6]},
                            "outputs": {"seg_glob": ["B", "G"], "seg_local": ["B", "N", "H"]}, "max_abs_err": err_seg},
            "frustum_head": {"file": GRAPH_FILES["frustum_head"],
                             "inputs": {"points": ["B", "N", 6], "one_hot": ["B", nc], "seg_glob": ["B", "G"],
                                        "seg_local": ["B", "N", "H"]},
                             "outputs": list(HEAD_OUTPUTS), "max_abs_err": err_head,
                             "frame": "frustum frame F (metres, radians); probs background last"},
            "frustum_box": {"file": GRAPH_FILES["frustum_box"],
                            "inputs": {"points": ["B", "N", 6], "one_hot": ["B", nc], "seg_glob": ["B", "G"],
                                       "seg_local": ["B", "N", "H"]},
                            "outputs": list(HEAD_OUTPUTS), "max_abs_err": err_box,
                            "frame": "as frustum_head, without the shape branch (prim_* zeros)"},
        },
    })
    return paths


def export_classifier_graph(model: Any, folder: str | Path) -> Path:
    """Export (and check) the proposal classifier's calibrated probabilities (an eval-mode
    :class:`~shape_detector.model.classifier.ProposalClassifier`) into ``folder``."""
    import torch

    from .classifier_inputs import GLOBAL_FEATURES, POINT_CHANNELS

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _, _, ClassifierGraph = _wrappers()
    graph = ClassifierGraph(model).eval()
    n, g = int(model.config.num_points), len(GLOBAL_FEATURES)

    def inputs(b: int) -> tuple:
        gen = torch.Generator().manual_seed(b)
        return torch.randn(b, n, POINT_CHANNELS, generator=gen), torch.randn(b, g, generator=gen)

    path = folder / GRAPH_FILES["classifier"]
    _export(graph, inputs(2), path, {"points": {0: "batch", 1: "points"}, "globals": {0: "batch"}},
            {"probs": {0: "batch"}})
    err = _check(path, graph, inputs, ["points", "globals"], CHECK_ATOL)
    _write_meta(folder, {
        "classifier_config": model.config.to_dict(),
        "graphs": {"classifier": {"file": GRAPH_FILES["classifier"],
                                  "inputs": {"points": ["B", "N", POINT_CHANNELS], "globals": ["B", g]},
                                  "outputs": {"probs": ["B", model.config.num_classes + 1]},
                                  "max_abs_err": err}},
    })
    return path


def _complete(folder: Path, names: tuple[str, ...]) -> dict[str, Any] | None:
    meta = read_meta(folder)
    if meta is None or not all(n in meta.get("graphs", {}) and (folder / GRAPH_FILES[n]).is_file() for n in names):
        return None
    return meta


def ensure_graphs(folder: Path, names: tuple[str, ...], export: Callable[[], Any]) -> dict[str, Any] | None:
    """``graphs.json`` of ``folder`` once it holds the graphs ``names``; when it does not,
    ``export()`` runs first, under :func:`cache_lock` and only if no other process exported
    them while this one waited. None when the export left them incomplete."""
    info = _complete(folder, names)
    if info is None:
        with cache_lock(folder):
            info = _complete(folder, names)  # another process may have exported meanwhile
            if info is None:
                export()
                info = _complete(folder, names)
    return info


def frustum_graphs(weights: str | Path | None, load_model) -> tuple[Path, dict[str, Any], Any]:
    """``(folder, graphs.json, model or None)``: the cached frustum graphs of ``weights``
    (keyed by the file's sha256), exported first when missing; ``load_model()`` ->
    ``(eval-mode network, meta)`` is called only then (it imports torch), or always when
    ``weights`` is None (the key is then the module's state)."""
    model, meta = None, {}
    if weights is None:
        model, meta = load_model()
        digest = module_digest(model)
    else:
        digest = sha256_file(weights)
    folder = cache_dir("frustum", digest)

    def export() -> None:
        nonlocal model, meta
        if model is None:
            model, meta = load_model()
        export_frustum_graphs(model, folder, {"tasks": meta.get("tasks")})

    info = ensure_graphs(folder, FRUSTUM_GRAPHS, export)
    if info is None:
        raise RuntimeError(f"export to {folder} left no usable graphs")
    return folder, info, model


def classifier_graph(model: Any) -> Path:
    """The cached classifier graph of ``model`` (keyed by its state's sha256), exported first
    when missing."""
    folder = cache_dir("classifier", module_digest(model))
    ensure_graphs(folder, ("classifier",), lambda: export_classifier_graph(model, folder))
    return folder / GRAPH_FILES["classifier"]
