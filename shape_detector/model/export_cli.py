"""``shape-detector export-onnx``: the inference graphs as ONNX files, for deployment elsewhere.

Writes into ``--out``: ``frustum_seg.onnx`` and ``frustum_head.onnx`` (the frustum network's
first and class-given passes, see :mod:`.onnx_export`), ``classifier.onnx`` (the proposal
classifier, unless ``--classifier none``; by default the one trained on ``--proposal-source``'s
candidates, as the detector picks it) and ``graphs.json``: every graph's inputs and
outputs (names, axes: ``B`` batch, ``N`` points), the model configuration, the weights'
sha256 and the largest difference from PyTorch measured on random inputs. Each graph has a
dynamic batch axis and is checked in onnxruntime against PyTorch before it is kept. Needs
torch and the ``onnx`` package (running the files needs only onnxruntime).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..detector_config import BUILTIN_PROPOSAL_SOURCES, DetectorConfig


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Options of ``export-onnx``."""
    p.add_argument("--out", required=True, help="folder to write the graphs and graphs.json into (created)")
    p.add_argument("--weights", default=None, help="frustum network weights (default: the packaged ones)")
    p.add_argument("--classifier", default=None,
                   help="proposal classifier weights (default: the packaged ones; 'none': skip it)")
    p.add_argument("--proposal-source", default=DetectorConfig().proposal_source, choices=BUILTIN_PROPOSAL_SOURCES,
                   help="the built-in proposer the graphs will serve: picks the default classifier "
                        "(hybrid: classifier_hybrid.pt beside the weights where there is one; default: the "
                        "detector's default, %(default)s)")


def classifier_path(weights: Path, classifier: str | Path | None, proposal_source: str | None = None) -> Path | None:
    """The classifier file to export: ``classifier`` when given (None for ``"none"``), else the
    one beside ``weights`` that the detector would load for ``proposal_source`` (None: the
    detector's default; :func:`~shape_detector.detector.packaged_classifier`); None when there is none.
    FileNotFoundError for a given file that is missing."""
    if str(classifier) == "none":
        return None
    if classifier:
        path = Path(classifier)
        if not path.is_file():
            raise FileNotFoundError(f"classifier file {path} not found")
        return path
    from ..detector import packaged_classifier

    path = packaged_classifier(proposal_source or DetectorConfig().proposal_source, weights.parent)
    return path if path.is_file() else None


def export_all(out: str | Path, weights: str | Path | None = None, classifier: str | Path | None = None,
               proposal_source: str | None = None) -> dict:
    """Export the frustum graphs of ``weights`` (None: packaged) and, unless ``classifier`` is
    ``"none"``, the classifier graph (:func:`classifier_path`) into ``out``; returns the written
    ``graphs.json``. FileNotFoundError for a missing weights file."""
    from .classifier import load_classifier
    from .io import load_weights
    from ..digests import sha256_file
    from .onnx_export import META_FILE, export_classifier_graph, export_frustum_graphs
    from .predictor import default_weights_path

    out = Path(out)
    wpath = Path(weights) if weights else default_weights_path()
    if not wpath.is_file():
        raise FileNotFoundError(f"weights file {wpath} not found")
    cpath = classifier_path(wpath, classifier, proposal_source)  # None: the frustum graphs alone
    model, meta = load_weights(wpath, "cpu")
    export_frustum_graphs(model.eval().fuse_batchnorm(), out, {
        "tasks": meta.get("tasks"), "weights_file": wpath.name, "weights_sha256": sha256_file(wpath),
    })
    if cpath is not None:
        export_classifier_graph(load_classifier(cpath)[0].eval().fuse_batchnorm(), out)
    info = json.loads((out / META_FILE).read_text())
    if cpath is not None:
        info["classifier_sha256"] = sha256_file(cpath)
        info["classifier_file"] = cpath.name
        (out / META_FILE).write_text(json.dumps(info, indent=2, default=str))
    return info


def main(args: argparse.Namespace) -> int:
    """Run ``export-onnx``; 0 on success, 2 on a missing file or package."""
    try:
        info = export_all(args.out, args.weights, args.classifier, args.proposal_source)
    except (FileNotFoundError, ImportError) as e:
        print(f"shape-detector export-onnx: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    for name, g in info.get("graphs", {}).items():
        print(f"{out / g['file']}: {name}, inputs {list(g['inputs'])}, max |onnxruntime - torch| "
              f"{float(g['max_abs_err']):.2g}")
    print(f"{out / 'graphs.json'}: inputs, outputs and model configuration")
    return 0
