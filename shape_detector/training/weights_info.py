"""``shape-detector weights-info PATH [--json]``: what a weights file is and where it came from.

Reads any shape_detector weights file (network, proposal classifier or training checkpoint)
with ``torch.load(weights_only=True)`` and prints its format, version, size, sha256,
parameter count, the model config and the provenance block (git commit, recipe hash, phase,
data seeds, parents' sha256, metrics at save).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: metrics printed in the text form (all are in the JSON form)
_KEY_METRICS = ("box_iou", "box_iou_agnostic", "shape_iou", "shape_iou_gtbox", "cls_acc_agnostic", "seg_acc",
                "acc", "acc_objects", "objectness_acc", "nll")


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``weights-info``."""
    p.add_argument("path", type=Path, help="weights file (.pt)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def weights_info(path: str | Path) -> dict[str, Any]:
    """The description of a weights file as a plain dict (see the module docstring)."""
    from ..model.io import read_blob
    from ..digests import sha256_file

    p = Path(path)
    blob = read_blob(p)
    sd = blob["state_dict"]
    info: dict[str, Any] = {
        "path": str(p),
        "bytes": p.stat().st_size,
        "sha256": sha256_file(p),
        "format": blob.get("format"),
        "version": blob.get("version"),
        "tensors": len(sd),
        "parameters": int(sum(int(v.numel()) for v in sd.values())),
        "dtypes": sorted({str(v.dtype).replace("torch.", "") for v in sd.values()}),
        "config": blob.get("model_config", blob.get("config", {})),
        "provenance": blob.get("provenance", {}),
    }
    meta = blob.get("meta", {})
    for k in ("tasks", "epoch", "seed"):
        if k in meta:
            info[k] = meta[k]
    return info


def format_text(info: dict[str, Any]) -> str:
    """Human-readable lines of :func:`weights_info`'s dict."""
    prov = info.get("provenance") or {}
    lines = [
        f"file:        {info['path']} ({info['bytes']:,} B)",
        f"sha256:      {info['sha256']}",
        f"format:      {info['format']} version {info['version']}",
        f"tensors:     {info['tensors']} ({info['parameters']:,} values; {', '.join(info['dtypes'])})",
    ]
    if not prov:
        lines.append("provenance:  none recorded")
        return "\n".join(lines)
    lines += [
        f"phase:       {prov.get('phase')}" + ("   (provenance reconstructed)" if prov.get("reconstructed") else ""),
        f"git commit:  {prov.get('git_commit')}",
        f"recipe:      {prov.get('recipe')}",
        f"recipe hash: {prov.get('recipe_sha256')}",
        f"created:     {prov.get('created_utc')} (torch {prov.get('torch_version')}, "
        f"{prov.get('world_size', 1)} process(es))",
    ]
    for d in prov.get("data") or []:
        lines.append(f"data:        {d.get('path')}: seed {d.get('seed')}, {d.get('frames')} frames, "
                     f"generator {d.get('generator_version')}")
    for par in prov.get("parents") or []:
        lines.append(f"parent:      {par.get('phase')} sha256 {par.get('sha256')}")
    mets = prov.get("metrics") or {}
    shown = [f"{k} {mets[k]:.4f}" for k in _KEY_METRICS if isinstance(mets.get(k), (int, float))]
    if shown:
        lines.append("metrics:     " + ", ".join(shown))
    if prov.get("notes"):
        lines.append(f"notes:       {prov['notes']}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Print the description of ``args.path``; exit 2 with one line for a bad file."""
    try:
        info = weights_info(args.path)
    except (OSError, ValueError) as e:
        print(f"weights-info: {e}", file=sys.stderr)
        return 2
    print(json.dumps(info, indent=1, default=str) if args.json else format_text(info))
    return 0


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    sys.exit(main(parser.parse_args()))
