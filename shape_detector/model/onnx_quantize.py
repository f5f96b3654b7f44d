"""int8 versions of the frustum network's box and head graphs.

Which passes run in int8 follows the ``precision`` setting (:func:`quantized_passes`):
``"int8"``: all; ``"auto"``: the class-agnostic first pass over built-in proposals
(``frustum_box``: its boxes rank and deduplicate proposals but are never published) and the
pass over given 2D boxes whose class came with them (``frustum_head``), but not the
class-given second pass over built-in proposals, nor a class-agnostic pass whose boxes are
published; ``"fp32"``: none. (int8 moved the given-box rows by at most 0.5 points, the
second pass's by 0.7-0.9 points at mAP@0.5: docs/model_card.md.)

ONNX Runtime's dynamic quantisation: the weights of the selected matrix products are stored
as int8 (per output channel), their inputs quantised to uint8 per batch at run time. Only the
wide per-point layers are quantised, and not the segmentation's: :func:`int8_nodes` takes the
``MatMul`` nodes with a constant weight of at least :data:`MIN_CHANNELS` input channels and
more than two outputs, outside the segmentation PointNet and its head. Those are most of the
arithmetic (the T-Net, box, context, second-box and shape PointNets). The segmentation is left
in float32 because a flipped mask point changes which points the later PointNets gather, and
the box moves by centimetres; the later layers' int8 error moves it by millimetres.

Weights use 7 bits (``reduce_range``): on x86 CPUs without VNNI the uint8 x int8 products are
summed in pairs in 16 bits, which 8-bit weights can overflow, so with 7 bits every x86 CPU gives
the same result. The ``frustum_seg`` graph is shared with float32.

Needs the ``onnx`` package (``onnxruntime.quantization`` imports it) to build; running the
files needs only onnxruntime. Measured speed and accuracy: docs/model_card.md.
"""

from __future__ import annotations

import logging
import os
import shutil
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .onnx_export import GRAPH_FILES, _write_meta, cache_lock, read_meta

#: the graphs that have an int8 version
INT8_GRAPHS = ("frustum_box", "frustum_head")
#: matrix products with fewer input channels stay float32 (the first layers see raw xyz)
MIN_CHANNELS = 64
#: nodes whose names contain this belong to the segmentation and stay float32
SEGMENTATION_TAG = "seg_"
#: bump when the selection or the settings change (cached int8 graphs are rebuilt)
INT8_VERSION = 1


#: the passes whose shape head can run in int8: over given 2D boxes with their class, the
#: class-given second pass over built-in proposals, a class-agnostic pass whose boxes are published
HEAD_PASSES = ("given", "second", "agnostic")


def quantized_passes(precision: str) -> frozenset[str]:
    """The :data:`HEAD_PASSES` whose head runs in int8 under ``precision`` (module docstring;
    the never-published first pass, ``frustum_box``, runs in int8 under both)."""
    return frozenset({"int8": HEAD_PASSES, "auto": ("given",)}.get(precision, ()))


def quantized_graphs(precision: str) -> tuple[str, ...]:
    """The graphs whose int8 versions run under ``precision`` (module docstring)."""
    return INT8_GRAPHS if precision in ("int8", "auto") else ()


def int8_file(name: str) -> str:
    """File name of graph ``name``'s int8 version (``frustum_head`` -> ``frustum_head.int8.onnx``)."""
    return GRAPH_FILES[name].replace(".onnx", ".int8.onnx")


def int8_nodes(model: Any) -> list[str]:
    """Names of the ``MatMul`` nodes of an ``onnx.ModelProto`` that :mod:`this module
    <.onnx_quantize>` quantises (see the module docstring)."""
    weights = {t.name: tuple(t.dims) for t in model.graph.initializer}
    out = []
    for node in model.graph.node:
        if node.op_type != "MatMul" or SEGMENTATION_TAG in node.name:
            continue
        dims = [weights[i] for i in node.input if i in weights]
        if dims and len(dims[0]) == 2 and dims[0][0] >= MIN_CHANNELS and dims[0][1] > 2:
            out.append(node.name)
    return out


@contextmanager
def quiet_quantiser() -> Iterator[None]:
    """Silence onnxruntime's quantiser (its warnings and "consider pre-processing" notices)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        level = logging.getLogger().level
        logging.getLogger().setLevel(logging.ERROR)
        try:
            yield
        finally:
            logging.getLogger().setLevel(level)


def quantize_graph(src: str | Path, dst: str | Path) -> int:
    """Write the int8 version of the ONNX graph ``src`` to ``dst``; returns how many matrix
    products were quantised. ImportError without the ``onnx`` package."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    nodes = int8_nodes(onnx.load(str(src), load_external_data=False))
    dst = Path(dst)
    tmp = dst.with_name(dst.name + f".{os.getpid()}.tmp")
    if not nodes:  # a narrow network: nothing to quantise (an empty list would mean "all" to the quantiser)
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
        return 0
    with quiet_quantiser():
        quantize_dynamic(str(src), str(tmp), weight_type=QuantType.QInt8, per_channel=True, reduce_range=True,
                         nodes_to_quantize=nodes, op_types_to_quantize=["MatMul"])
    os.replace(tmp, dst)
    return len(nodes)


def int8_graphs(folder: str | Path, names: tuple[str, ...] = INT8_GRAPHS) -> dict[str, Path]:
    """The int8 versions of the graphs ``names`` in an export ``folder`` (next to their float32
    graphs), built first where ``graphs.json`` does not record this :data:`INT8_VERSION` of them."""
    folder = Path(folder)
    paths = {name: folder / int8_file(name) for name in names}
    if not _missing(folder, paths):
        return paths
    with cache_lock(folder):  # the quantiser writes and deletes a file beside the source graph
        _build_int8(folder, _missing(folder, paths))
    return paths


def _missing(folder: Path, paths: dict[str, Path]) -> dict[str, Path]:
    """Those of ``paths`` (graph name -> int8 file) not built, or not recorded in ``graphs.json``
    with this :data:`INT8_VERSION`."""
    known = (read_meta(folder) or {}).get("graphs", {})
    return {name: path for name, path in paths.items()
            if not (path.is_file() and (known.get(name + "_int8") or {}).get("int8_version") == INT8_VERSION)}


def _build_int8(folder: Path, paths: dict[str, Path]) -> None:
    """Quantise the graphs ``paths`` names and record them in ``graphs.json``."""
    known = (read_meta(folder) or {}).get("graphs", {})
    built: dict[str, Any] = {}
    for name, path in paths.items():
        count = quantize_graph(folder / GRAPH_FILES[name], path)
        src = known.get(name) or {}
        built[name + "_int8"] = {"file": path.name, "from": GRAPH_FILES[name], "int8_version": INT8_VERSION,
                                 "inputs": src.get("inputs"), "outputs": src.get("outputs"),
                                 "quantized_matmuls": count, "weights": "int8 per output channel, 7 bits",
                                 "activations": "uint8 per batch, dynamic"}
    if built:
        _write_meta(folder, {"graphs": built})
