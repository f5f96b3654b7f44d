"""The int8 version of the learned 2D proposer's network.

ONNX Runtime's static quantisation in QDQ form: weights int8 per output channel, activations
uint8 with ranges calibrated on network inputs from generated frames. Weights use 7 bits
(``reduce_range``): on x86 CPUs without VNNI, ONNX Runtime sums the uint8 x int8 products in
pairs in 16 bits, which 8-bit weights can overflow, so with 7 bits every x86 CPU gives the
same result. Needs the ``onnx`` package to build; running the file needs only onnxruntime.
Measured speed and recall: docs/model_card.md.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

#: bump when the quantisation settings change (the provenance records it)
INT8_VERSION = 1


def int8_path(path: str | Path) -> Path:
    """The int8 version's file beside the network ``path`` (``proposer2d.onnx`` ->
    ``proposer2d.int8.onnx``)."""
    path = Path(path)
    return path.with_name(path.name.removesuffix(".onnx") + ".int8.onnx")


def provenance_path(path: str | Path) -> Path:
    """The provenance JSON beside a network file (``x.onnx`` -> ``x.onnx.json``)."""
    return Path(str(path) + ".json")


def int8_source_matches(int8_file: str | Path, source: str | Path) -> bool:
    """Whether the provenance of ``int8_file`` names ``source``'s sha256 (False without one)."""
    from ..digests import sha256_file

    try:
        meta = json.loads(provenance_path(int8_file).read_text())
    except (OSError, ValueError):
        return False
    return meta.get("source_sha256") == sha256_file(source) and meta.get("int8_version") == INT8_VERSION


class _Inputs:
    """Calibration inputs, one frame at a time (onnxruntime's ``CalibrationDataReader``)."""

    def __init__(self, inputs: np.ndarray) -> None:
        self._it = iter(np.asarray(inputs, dtype=np.float32))

    def get_next(self) -> dict[str, np.ndarray] | None:
        x = next(self._it, None)
        return None if x is None else {"input": x[None]}


def quantize(source: str | Path, inputs: np.ndarray, dst: str | Path | None = None,
             **provenance: Any) -> Path:
    """Write the int8 version of the proposer network ``source`` (default beside it,
    :func:`int8_path`), calibrated on ``inputs`` (N,5,H,W) as :func:`~.learned.prepare_input`
    gives them, and its provenance JSON (``provenance`` adds entries); returns its path."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from ..digests import sha256_file
    from ..model.onnx_quantize import quiet_quantiser

    source = Path(source)
    dst = int8_path(source) if dst is None else Path(dst)
    if len(inputs) == 0:
        raise ValueError("quantize: no calibration inputs")
    with tempfile.TemporaryDirectory() as tmp, quiet_quantiser():
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(source), str(pre))
        out = Path(tmp) / "int8.onnx"
        quantize_static(str(pre), str(out), _Inputs(inputs), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        reduce_range=True, calibrate_method=CalibrationMethod.MinMax)
        tmp_dst = dst.with_name(dst.name + f".{os.getpid()}.tmp")
        tmp_dst.write_bytes(out.read_bytes())
        os.replace(tmp_dst, dst)
    meta = {"source": source.name, "source_sha256": sha256_file(source), "int8_version": INT8_VERSION,
            "calibration_frames": int(len(inputs)), "sha256": sha256_file(dst),
            "weights": "int8 per output channel, 7 bits", "activations": "uint8, static (min-max calibration)",
            **provenance}
    provenance_path(dst).write_text(json.dumps(meta, indent=2) + "\n")
    return dst
