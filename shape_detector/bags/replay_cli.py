"""The offline ``shape-detector replay IN -o OUT`` run: output checks, signals, exit status.

Exit status: 0 done; 1 error (unreadable or damaged input, output not writable,
detector not created); 2 usage (bad option, output would overwrite the input);
3 frames were read but every one was skipped; 130 / 143 stopped by SIGINT / SIGTERM
(the output is finalised with the frames written so far).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .output_safety import (
    EXIT_SIGINT,
    EXIT_SIGTERM,
    OutputError,
    PartialOutput,
    StopSignals,
    UnsafeOutputError,
    check_output_path,
)

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_ALL_SKIPPED = 0, 1, 2, 3

EXIT_STATUS_HELP = (
    "exit status: 0 done; 1 error (unreadable or damaged input, output not writable); 2 usage "
    "(bad option, output would overwrite the input); 3 frames were read but every one was skipped "
    "(see the 'skipped:' line); 130 / 143 stopped by SIGINT / SIGTERM (output finalised with the "
    "frames written so far)"
)

_PROG = "shape-detector replay"


def _err(msg: str) -> None:
    print(f"{_PROG}: {msg}", file=sys.stderr)


def _check_output_early(args: argparse.Namespace) -> int | None:
    """Refuse an unsafe or existing output before the (slow) detector is built."""
    try:
        check_output_path(args.bag, args.out)
        PartialOutput(args.out, args.overwrite).check()
    except (OSError, ValueError) as e:  # UnsafeOutputError and OutputError included
        return _exit_for(e, f"cannot write output {args.out!r}: ")
    return None


def _exit_for(e: Exception, os_prefix: str = "") -> int:
    """Print one line for an expected error and return its exit status (no traceback)."""
    from .source import BagReadError

    if isinstance(e, UnsafeOutputError):
        _err(f"{e}; choose another -o/--out")
        return EXIT_USAGE
    if isinstance(e, (OutputError, FileNotFoundError, FileExistsError, ValueError, BagReadError)):
        _err(str(e))
    else:
        err = e if isinstance(e, OSError) else OSError(str(e))
        _err(os_prefix + f"{err.strerror or err}" + (f": {err.filename!r}" if err.filename and not os_prefix else ""))
    return EXIT_ERROR


def _exit_status(summary: Any) -> int:
    if summary.interrupted:
        _err(f"interrupted by {summary.interrupted}: {summary.frames_out} frame(s) written to {summary.out_path}")
        return EXIT_SIGTERM if summary.interrupted == "SIGTERM" else EXIT_SIGINT
    if summary.error:
        _err(summary.error)
        return EXIT_ERROR
    if summary.damage:
        _err(f"input has {len(summary.damage)} damaged chunk(s), skipped: " + "; ".join(summary.damage))
        return EXIT_ERROR
    if summary.all_skipped:
        why = ", ".join(f"{k}: {v}" for k, v in summary.skipped.most_common()) or "no synchronised frames"
        _err(f"every frame was skipped ({why}); {summary.frames_out} empty marker message(s) written")
        return EXIT_ALL_SKIPPED
    return EXIT_OK


def run_offline(args: argparse.Namespace, make_detector: Any, replay_bag: Any) -> int:
    """Run the offline replay for parsed ``args``; returns the exit status."""
    try:
        return _run(args, make_detector, replay_bag)
    except KeyboardInterrupt:  # a second signal: stop at once, the partial output is gone
        _err("interrupted twice: stopped at once; nothing written")
        return EXIT_SIGINT


def _run(args: argparse.Namespace, make_detector: Any, replay_bag: Any) -> int:
    from ..config_cli import config_from_args
    from ..process_detector import close_detector

    if (rc := _check_output_early(args)) is not None:
        return rc
    proposals = args.proposals or args.proposal_source or ("external" if args.detections2d else None)
    if proposals == "external" and not args.detections2d:
        _err("--proposals external needs --detections2d TOPIC")
        return EXIT_USAGE
    try:  # without a choice, the preset's proposals
        config = config_from_args(args, **({"proposal_source": proposals} if proposals else {}))
    except ValueError as e:
        _err(str(e))
        return EXIT_USAGE
    with StopSignals() as stop:
        try:
            detector = _detector(args, config, make_detector)
        except Exception as e:  # noqa: BLE001
            _err(f"cannot create the detector: {type(e).__name__}: {e}")
            return EXIT_ERROR
        try:
            rc = _replay(args, detector, replay_bag, stop)
        finally:
            close_detector(detector)
    return rc


def _detector(args: argparse.Namespace, config: Any, make_detector: Any) -> Any:
    """The detector: in ``--processes`` worker processes (started and warmed up), else here."""
    if not getattr(args, "processes", 0):
        return make_detector(config, args.detector)
    from ..process_detector import ProcessDetector

    return ProcessDetector.started(config, args.processes, args.detector or "")


def _replay(args: argparse.Namespace, detector: Any, replay_bag: Any, stop: Any) -> int:
    """Replay with a built detector; the exit status."""
    from ..replay import scene_options
    from .source import BagReadError

    if stop.name:
        _err(f"interrupted by {stop.name} before any frame was read; nothing written")
        return EXIT_SIGTERM if stop.name == "SIGTERM" else EXIT_SIGINT
    topics = {k: getattr(args, k) for k in ("image", "depth", "camera_info", "imu", "detections2d")}
    try:
        summary = replay_bag(
            args.bag, args.out, detector, topics, progress=not args.no_progress, slop=args.slop,
            queue_size=args.queue_size, depth_scale=args.depth_scale, up=args.up,
            size_mismatch=args.size_mismatch, write_detections=not args.no_detections,
            overwrite=args.overwrite, copy_input=not args.no_copy, should_stop=stop,
            scene=scene_options(args),
        )
    except (OSError, ValueError, BagReadError) as e:
        return _exit_for(e)
    _print_summary(summary, args.json)
    return _exit_status(summary)


def _print_summary(summary: Any, as_json: bool) -> None:
    if as_json:
        import json

        print(json.dumps(summary.as_dict(), indent=2))
    else:
        print(summary.format())
    sys.stdout.flush()
