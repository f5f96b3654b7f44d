"""The ``shape-detector`` command: one entry point, one module per subcommand.

Each subcommand lives in its own module exposing ``configure_parser(parser)`` and
``main(args) -> int``; modules are imported only when their subcommand runs, so
``shape-detector --help`` stays fast and torch is not loaded for bag work that needs none.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

#: subcommand -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("shape_detector.demo", "run the detector on a bag and write an output bag + PNG overlay"),
    "replay": ("shape_detector.replay", "run the detector over a recorded bag, or --play it live"),
    "synth": ("shape_detector.synth.cli", "generate RGB-D scenes: dataset shards, sample bags, figures"),
    "train": ("shape_detector.training.cli", "train the frustum network on generated data"),
    "train-classifier": ("shape_detector.training.classifier_cli",
                         "train the proposal classifier on the network's built-in-proposal candidates"),
    "train-proposer": ("shape_detector.training.train_proposer",
                       "train the learned 2D proposer on generated frames (writes an ONNX file)"),
    "prune": ("shape_detector.training.prune",
              "narrow a trained network's widest per-point layers (structured pruning), to fine-tune"),
    "weights-info": ("shape_detector.training.weights_info", "print a weights file's format, provenance and metrics"),
    "evaluate": ("shape_detector.evaluation.cli", "evaluate weights on a held-out generated set"),
    "bench": ("shape_detector.bench", "benchmarks that print numbers (synth, network, proposals, node)"),
    "evaluate-scene": ("shape_detector.evaluation.scene_cli",
                       "score the scene map (final-map mAP, duplicates, id switches, jitter, grid IoU) on walk-throughs"),
    "train-track-classifier": ("shape_detector.evaluation.track_classifier_cli",
                               "fit the scene map's track classifier on generated walk-throughs"),
    "evaluate-ar": ("shape_detector.evaluation.ar_cli",
                    "score the AR queries (ray casts, collision, paths) on generated walk-throughs"),
    "export": ("shape_detector.export.cli", "export a scene map JSON to .glb / .gltf / .obj for game engines"),
    "export-onnx": ("shape_detector.model.export_cli", "write the ONNX graphs and graphs.json for deployment"),
    "config": ("shape_detector.config_docs", "print the settings as a ROS 2 parameters file (--preset) or table"),
    "config-path": ("shape_detector.cli", "print the path of a packaged config file"),
}


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Arguments of ``shape-detector config-path``: the config file name under the package ``config/``."""
    p.add_argument("name", nargs="?", default="fastdds_shm.xml", help="file name under the package config/")


def main_config_path(args: argparse.Namespace) -> int:
    """Print the absolute path of packaged config file ``args.name``; exit code 2 when it does not exist."""
    path = Path(__file__).resolve().parent / "config" / args.name
    if not path.is_file():
        print(f"no packaged config file {args.name!r} (in {path.parent})", file=sys.stderr)
        return 2
    print(path)
    return 0


def _usage() -> str:
    lines = ["usage: shape-detector COMMAND [options]   (shape-detector COMMAND --help)", "", "commands:"]
    width = max(len(name) for name in SUBCOMMANDS)
    lines += [f"  {name:<{width}}  {help_}" for name, (_, help_) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``shape-detector COMMAND ...``; returns the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"shape-detector: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, help_ = SUBCOMMANDS[name]
    parser = argparse.ArgumentParser(prog=f"shape-detector {name}", description=help_)
    if name == "config-path":
        configure_parser(parser)
        return main_config_path(parser.parse_args(rest))
    module = importlib.import_module(module_name)
    module.configure_parser(parser)
    args = parser.parse_args(rest)
    return int(module.main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
