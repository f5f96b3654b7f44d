"""``shape-detector replay``: run the detector over a recorded bag, or play a bag live.

Offline (``shape-detector replay IN -o OUT``): every synchronised frame of ``IN`` goes
through the detector (nothing is dropped offline) and ``OUT`` - a rosbag2 MCAP - gets the
input topics plus ``/shape_detector/markers`` (and ``/shape_detector/detections``) at the
input stamps. Library use::

    from shape_detector.replay import replay_bag
    summary = replay_bag("bags/sample", "out/sample_detections", detector)
    print(summary.format())

Live (``shape-detector replay IN --play``): publishes the bag's topics with rclpy at real
or scaled rate (``--rate``), optionally re-stamped to the current time (``--restamp``),
so a running ``detector_node`` can be fed from a bag where ``ros2 bag play`` is missing.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .bag_io import (
    DETECTIONS_TOPIC,
    MARKERS_TOPIC,
    BagFrameReader,
    BagReadError,
    TopicSelection,
    convert_message,
    open_bag,
)
from .bags.output_safety import SafeOutputBag
from .bags.replay_loop import check_replay_args, count_damage, replay_loop
from .model.config import PRECISIONS

# =====================================================================================
# offline replay
# =====================================================================================


@dataclass
class ReplaySummary:
    """What a replay did. ``frames_in``: colour images read; ``synced``: synchronised
    sets; ``frames_out``: marker messages written (one per synchronised set, empty for
    sets that could not be used - see ``skipped``); ``error``: the bag damage message when
    the input was cut short (everything before it was processed and written)."""

    in_path: str
    out_path: str
    topics: TopicSelection | None = None
    messages_in: int = 0
    frames_in: int = 0
    depth_in: int = 0
    synced: int = 0
    frames_out: int = 0
    objects: int = 0
    objects_per_class: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    detect_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    copied: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)
    notes: Counter = field(default_factory=Counter)
    recovered: bool = False
    error: str | None = None
    interrupted: str | None = None
    damage: list[str] = field(default_factory=list)
    detected: int = 0

    @property
    def ok(self) -> bool:
        return self.error is None and not self.damage

    @property
    def all_skipped(self) -> bool:
        """Frames were read, but not one reached the detector."""
        return self.detected == 0 and (self.frames_in > 0 or sum(self.skipped.values()) > 0)

    @property
    def ms_per_frame(self) -> float:
        return float(np.mean(self.detect_ms)) if self.detect_ms else 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "in": self.in_path,
            "out": self.out_path,
            "topics": None if self.topics is None else vars(self.topics),
            "messages_in": self.messages_in,
            "frames_in": self.frames_in,
            "synced": self.synced,
            "frames_out": self.frames_out,
            "objects": self.objects,
            "objects_per_class": dict(self.objects_per_class),
            "skipped": dict(self.skipped),
            "ms_per_frame": round(self.ms_per_frame, 2),
            "wall_s": round(self.wall_s, 3),
            "detected": self.detected,
            "error": self.error,
            "damage": list(self.damage),
            "interrupted": self.interrupted,
        }

    def format(self) -> str:
        t = self.topics
        lines = [f"replay {self.in_path} -> {self.out_path}"]
        if t is not None:
            lines.append(f"  topics: image {t.image}, depth {t.depth}, camera_info {t.camera_info}"
                         + (f", imu {t.imu}" if t.imu else "") + (f", detections2d {t.detections2d}" if t.detections2d else ""))
        lines.append(
            f"  frames: {self.frames_in} in / {self.synced} synchronised / {self.frames_out} out"
            f"   ({self.messages_in} messages read{', recovered sequentially' if self.recovered else ''})"
        )
        if self.skipped:
            reasons = ", ".join(f"{k}: {v}" for k, v in self.skipped.most_common())
            lines.append(f"  skipped: {sum(self.skipped.values())} ({reasons})")
        per = ", ".join(f"{k} {v}" for k, v in self.objects_per_class.most_common()) or "none"
        lines.append(f"  objects: {self.objects} ({per})")
        if self.detect_ms:
            lines.append(
                f"  detector: {self.ms_per_frame:.1f} ms/frame (p95 {np.percentile(self.detect_ms, 95):.1f} ms); "
                f"wall {self.wall_s:.2f} s"
            )
        for note, n in self.notes.most_common(5):
            lines.append(f"  note ({n}x): {note}")
        for topic, why in self.skipped_topics.items():
            lines.append(f"  not copied: {topic}: {why}")
        for d in self.damage:
            lines.append(f"  DAMAGED (skipped): {d}")
        if self.error:
            lines.append(f"  ERROR: {self.error}")
            lines.append(f"  the {self.frames_out} frame(s) before the damage were written to {self.out_path}")
        if self.interrupted:
            lines.append(f"  interrupted by {self.interrupted}: {self.frames_out} frame(s) written to {self.out_path}")
        return "\n".join(lines)


class _Progress:
    """A one-line progress bar on stderr (redrawn at most 10x a second)."""

    def __init__(self, total: int | None, enabled: bool, stream: Any = None) -> None:
        self.total = total
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = 0.0
        self._last_pct = -1
        self.n = 0
        self.frames = 0

    def update(self, n: int, frames: int, force: bool = False) -> None:
        self.n, self.frames = n, frames
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        if self.total:
            frac = min(1.0, n / self.total)
            if not self.tty:  # log every 10 %
                pct = int(frac * 10)
                if pct == self._last_pct and not force:
                    return
                self._last_pct = pct
                self.stream.write(f"replay: {100 * frac:3.0f}%  {n}/{self.total} messages, {frames} frames\n")
                self.stream.flush()
                return
            width = 30
            bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
            self.stream.write(f"\r[{bar}] {100 * frac:3.0f}%  {n}/{self.total} msgs  {frames} frames")
        else:
            if not self.tty and not force:
                return
            self.stream.write(f"\r{n} msgs  {frames} frames" if self.tty else f"replay: {n} messages, {frames} frames\n")
        self.stream.flush()

    def done(self) -> None:
        if self.enabled:
            self.update(self.n, self.frames, force=True)
            if self.tty:
                self.stream.write("\n")
                self.stream.flush()


def _parse_up(up: Any) -> np.ndarray | None:
    if up is None:
        return None
    v = np.asarray([float(x) for x in (up.split(",") if isinstance(up, str) else up)], dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
        raise ValueError(f"up must be three finite numbers, not all zero, got {up!r}")
    return v / np.linalg.norm(v)


def replay_bag(
    in_path: str | Path,
    out_path: str | Path,
    detector: Any = None,
    topics: TopicSelection | dict[str, str] | None = None,
    progress: bool = True,
    *,
    slop: float = 0.02,
    queue_size: int = 30,
    depth_scale: float | None = None,
    up: Any = None,
    size_mismatch: str = "rescale",
    write_detections: bool = True,
    overwrite: bool = False,
    copy_input: bool = True,
    on_frame: Any = None,
    should_stop: Any = None,
) -> ReplaySummary:
    """Run ``detector`` over every synchronised frame of bag ``in_path`` and write
    ``out_path`` (rosbag2 MCAP): the input topics (``copy_input``) plus markers and
    detections at the input stamps.

    ``detector``: anything with ``detect(rgb, depth, K, boxes2d=None, up=None)``
    (default: a new :class:`shape_detector.detector.ShapeDetector`). ``topics``: a
    :class:`TopicSelection` or a dict with keys ``image, depth, camera_info, imu,
    detections2d`` (missing = chosen automatically). ``up``: fixed gravity-up vector
    (camera frame); else the IMU's when an imu topic is given, else estimated by the
    detector. ``depth_scale``: metres per raw depth unit (> 0; None = by encoding).
    ``on_frame(frame, prepared_or_None, objects)`` is called per frame.
    ``should_stop()``: polled between messages; a true value (e.g. ``'SIGTERM'``) ends
    the replay early with ``summary.interrupted`` set to it.

    The output is written under a temporary sibling name and renamed into place when
    finalised (also after damage or a stop); ``overwrite`` replaces an old output only
    then. An output that is, contains or lies inside the input is refused
    (``UnsafeOutputError``, a ValueError). Damage in the input ends the replay early
    with ``summary.error`` set; damaged chunks are skipped and listed in
    ``summary.damage``. Unusable frames (bad encoding, sizes, missing camera_info) get an
    empty MarkerArray and are counted in ``summary.skipped``. Raises FileNotFoundError /
    ValueError / BagReadError when nothing could be read, FileExistsError, and
    ``OutputError`` (an OSError naming the output) when the output cannot be written.
    """
    t0 = time.perf_counter()
    check_replay_args(depth_scale, slop, queue_size)
    up_vec = _parse_up(up)
    sel: dict[str, Any] = {}
    if isinstance(topics, TopicSelection):
        sel = {k: v for k, v in vars(topics).items() if v}
    elif topics:
        sel = {k: v for k, v in dict(topics).items() if v}
        unknown = set(sel) - {"image", "depth", "camera_info", "imu", "detections2d"}
        if unknown:
            raise ValueError(f"unknown topic roles {sorted(unknown)}")
    safe = SafeOutputBag(in_path, out_path, overwrite=overwrite, write_detections=write_detections)
    if detector is None:
        from .detector import ShapeDetector

        detector = ShapeDetector()
    summary = ReplaySummary(str(in_path), str(out_path))
    with BagFrameReader(in_path, slop=slop, queue_size=queue_size, **sel) as reader:
        summary.topics = reader.selection
        summary.recovered = reader.source.recovered
        bar = _Progress(reader.source.message_count, progress)
        with safe as out:
            try:
                replay_loop(reader, out, detector, summary, bar, copy_input=copy_input, up_vec=up_vec,
                            depth_scale=depth_scale, size_mismatch=size_mismatch, on_frame=on_frame,
                            should_stop=should_stop)
            finally:
                bar.done()
            count_damage(summary, reader.source, reader.selection.image)
            summary.copied = dict(out.counts)
            summary.skipped_topics = dict(out.skipped_topics)
    summary.wall_s = time.perf_counter() - t0
    return summary


# =====================================================================================
# live playback
# =====================================================================================


@dataclass
class PlaySummary:
    published: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0
    error: str | None = None


def _msg_class(msgtype: str) -> Any:
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _restamp(msg: Any, mapping: Any) -> bool:
    """Shift ``msg.header.stamp`` (and nested Detection headers) through ``mapping``."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None or not hasattr(stamp, "sec"):
        return False
    ns = mapping(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec))
    stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)
    for det in getattr(msg, "detections", []) or []:
        _restamp(det, mapping)
    return True


def play_bag(
    path: str | Path,
    rate: float = 1.0,
    *,
    topics: list[str] | None = None,
    remap: dict[str, str] | None = None,
    restamp: bool = False,
    loop: bool = False,
    clock: bool = False,
    wait_subscribers: float = 0.0,
    start_delay: float = 0.0,
    qos_depth: int = 10,
    context: Any = None,
    node_name: str = "shape_detector_player",
    should_stop: Any = None,
    log: Any = print,
) -> PlaySummary:
    """Publish a bag's messages with rclpy at ``rate`` x real time (``rate <= 0``: as
    fast as possible).

    ``topics``: only these (default all); ``remap``: ``{bag_topic: published_topic}``;
    ``restamp``: header stamps mapped to wall time (``now + (stamp - bag_start) / rate``;
    equal stamps stay equal; with ``rate <= 0`` publish time + (stamp - log time)) - needed to measure latency or for consumers that compare
    stamps with their clock; ``clock``: also publish ``/clock`` (bag or restamped time);
    ``wait_subscribers``: wait up to this many seconds until every published topic has a
    subscriber (or some have, unchanged for 1 s); ``loop``: repeat until interrupted. rclpy must be initialised in
    ``context`` (default: the global context; initialised and shut down here if needed).
    """
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy

    from msg_conversion.msgtypes import rosbags_types

    summary = PlaySummary()
    own_init = False
    if context is None and not rclpy.ok():
        rclpy.init()
        own_init = True
    node = rclpy.create_node(node_name, context=context) if context is not None else rclpy.create_node(node_name)
    remap = dict(remap or {})
    jazzy = rosbags_types().typestore
    t_start = time.perf_counter()
    try:
        source = open_bag(path)
        try:
            for d in source.damage:
                log(f"play: damaged chunk, not published: {d}")
            wanted = [t for t in source.topics if topics is None or t in topics]
            if topics:
                missing = [t for t in topics if t not in source.topics]
                if missing:
                    raise ValueError(f"topics not in the bag: {missing}; bag topics: {sorted(source.topics)}")
            qos = QoSProfile(depth=qos_depth, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
            pubs: dict[str, Any] = {}
            for t in wanted:
                msgtype = source.topics[t]
                try:
                    cls = _msg_class(msgtype)
                except (ImportError, AttributeError, ValueError) as e:
                    summary.skipped_topics[t] = f"no Python message class for {msgtype} ({e})"
                    continue
                pubs[t] = (node.create_publisher(cls, remap.get(t, t), qos), msgtype)
            for t, why in summary.skipped_topics.items():
                log(f"play: not publishing {t}: {why}")
            clock_pub = None
            if clock:
                from rosgraph_msgs.msg import Clock

                clock_pub = node.create_publisher(Clock, "/clock", 10)
            if wait_subscribers > 0:
                # until every topic has a subscriber, or some have and that set has been
                # stable for a second (topics nobody listens to do not hold playback up)
                deadline = time.monotonic() + wait_subscribers
                seen: frozenset = frozenset()
                stable_since = time.monotonic()
                while time.monotonic() < deadline:
                    now_seen = frozenset(t for t, (p, _) in pubs.items() if p.get_subscription_count() > 0)
                    if len(now_seen) == len(pubs):
                        break
                    if now_seen != seen:
                        seen, stable_since = now_seen, time.monotonic()
                    elif seen and time.monotonic() - stable_since > 1.0:
                        break
                    time.sleep(0.05)
                lonely = [t for t, (p, _) in pubs.items() if p.get_subscription_count() == 0]
                if len(lonely) == len(pubs):
                    log(f"play: no subscribers after {wait_subscribers:.1f} s")
                elif lonely:
                    log(f"play: no subscribers on {', '.join(remap.get(t, t) for t in lonely)}")
                time.sleep(0.3)  # let the subscribers' side of discovery settle too
            if start_delay > 0:
                time.sleep(start_delay)
            first_pass = True
            while True:
                src = source if first_pass else open_bag(path)
                first_pass = False
                bag_start: int | None = None
                wall0 = 0.0
                wall0_ns = 0
                try:
                    for m in src.messages(list(pubs)):
                        if (should_stop is not None and should_stop()) or not rclpy.ok(context=context):
                            return summary
                        if bag_start is None:
                            bag_start = m.log_time_ns
                            wall0 = time.perf_counter()
                            wall0_ns = time.time_ns()
                        if rate > 0:
                            target = wall0 + (m.log_time_ns - bag_start) / 1e9 / rate
                            delay = target - time.perf_counter()
                            if delay > 0:
                                time.sleep(delay)
                        pub, msgtype = pubs[m.topic]
                        data = m.raw
                        if rate > 0:
                            def mapping(ns: int, _b=bag_start, _w=wall0_ns) -> int:
                                return _w + int((ns - _b) / rate)
                        else:  # as fast as possible: stamps follow the publish time
                            def mapping(ns: int, _now=time.time_ns(), _log=m.log_time_ns) -> int:
                                return _now + (ns - _log)
                        if restamp or src.is_ros1:
                            try:
                                msg = src.deserialize(m.raw, msgtype)
                                if src.is_ros1:
                                    msg = convert_message(msg, msgtype, jazzy)
                                if restamp:
                                    _restamp(msg, mapping)
                                data = jazzy.serialize_cdr(msg, msgtype)
                            except BagReadError:
                                raise
                            except Exception as e:  # noqa: BLE001
                                if src.is_ros1:
                                    summary.skipped_topics.setdefault(m.topic, f"conversion failed: {e}")
                                    continue
                        if clock_pub is not None:
                            from rosgraph_msgs.msg import Clock

                            ns = mapping(m.log_time_ns) if restamp else m.log_time_ns
                            c = Clock()
                            c.clock.sec, c.clock.nanosec = divmod(ns, 1_000_000_000)
                            clock_pub.publish(c)
                        pub.publish(bytes(data))
                        summary.published += 1
                        summary.per_topic[m.topic] = summary.per_topic.get(m.topic, 0) + 1
                except BagReadError as e:
                    summary.error = str(e)
                    log(f"play: {e}")
                    return summary
                finally:
                    if src is not source:
                        src.close()
                if not loop:
                    break
            time.sleep(0.2)  # let the last messages leave before the publishers go
        finally:
            source.close()
    finally:
        summary.wall_s = time.perf_counter() - t_start
        node.destroy_node()
        if own_init:
            rclpy.try_shutdown()
    return summary


# =====================================================================================
# CLI
# =====================================================================================


def load_factory(spec: str) -> Any:
    """``'package.module:callable'`` -> the callable (a detector factory)."""
    if ":" not in spec:
        raise ValueError(f"detector factory {spec!r} must look like 'package.module:callable'")
    mod, _, attr = spec.partition(":")
    obj: Any = importlib.import_module(mod)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def make_detector(
    weights: str | None = None,
    device: str = "cpu",
    score_threshold: float = 0.3,
    max_objects: int = 25,
    proposals: str = "geometric",
    factory: str | None = None,
    workers: int = 2,
    precision: str = "fp32",
    classifier: str | None = None,
    refine: bool = True,
) -> Any:
    """The detector for the CLI and the node: ``ShapeDetector`` or ``factory(**same kwargs)``.

    ``proposals``: 'geometric' (built-in) or 'external' (2D boxes come with every frame;
    ShapeDetector is then built with ``proposals='none'``). ``classifier``: None = the
    packaged proposal classifier, 'none' = off, else a path; ``refine``: the class-given
    second pass (these two are passed to a factory only when not the defaults)."""
    from .detector import ShapeDetector, classifier_option

    if proposals not in ("geometric", "external", "none"):
        raise ValueError(f"proposals must be 'geometric' or 'external', got {proposals!r}")
    kwargs: dict[str, Any] = dict(weights=weights or None, device=device, score_threshold=score_threshold,
                                  max_objects=max_objects, proposals="none" if proposals == "external" else proposals,
                                  workers=workers, precision=precision)
    if (spec := classifier_option(classifier)) is not None:
        kwargs["classifier"] = spec
    if not refine:
        kwargs["refine"] = False
    if factory:
        return load_factory(factory)(**kwargs)
    return ShapeDetector(**kwargs)


def configure_parser(p: argparse.ArgumentParser) -> None:
    from .bags import cli_args as ca
    from .bags.replay_cli import EXIT_STATUS_HELP

    p.description = (
        "Run the detector over a bag (rosbag2 MCAP/sqlite3 directory or file, ROS 1 .bag) and write "
        "a rosbag2 MCAP with the input topics plus /shape_detector/markers and /shape_detector/detections; "
        "or, with --play, publish the bag live."
    )
    p.epilog = EXIT_STATUS_HELP
    p.add_argument("bag", type=ca.path_text, help="input bag: rosbag2 directory, .mcap, .db3 or ROS 1 .bag")
    p.add_argument("-o", "--out", type=ca.path_text,
                   help="output rosbag2 directory (MCAP); required unless --play; must not be, contain or lie "
                        "inside the input")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output bag (only once the new one is complete)")
    g = p.add_argument_group("topics (default: chosen automatically)")
    g.add_argument("--image", type=ca.topic, help="colour sensor_msgs/Image topic")
    g.add_argument("--depth", type=ca.topic, help="depth sensor_msgs/Image topic (16UC1 / 32FC1, registered to colour)")
    g.add_argument("--camera-info", dest="camera_info", type=ca.topic, help="colour sensor_msgs/CameraInfo topic")
    g.add_argument("--imu", type=ca.topic,
                   help="sensor_msgs/Imu topic for gravity-up (IMU in the camera optical frame)")
    g.add_argument("--detections2d", type=ca.topic,
                   help="vision_msgs/Detection2DArray topic with external 2D proposals")
    d = p.add_argument_group("detector")
    d.add_argument("--weights", type=ca.path_text, help="network weights (default: the packaged ones)")
    d.add_argument("--device", type=ca.device, default="cpu", help="auto, cpu, cuda, cuda:N or mps (default cpu)")
    d.add_argument("--score-threshold", type=ca.probability, default=0.3,
                   help="minimum object score, 0..1 (default 0.3)")
    d.add_argument("--max-objects", type=ca.int_at_least(1), default=25,
                   help="at most this many objects per frame, >= 1 (default 25)")
    d.add_argument("--precision", default="fp32", choices=PRECISIONS,
                   help="network arithmetic (bf16: faster on CPUs with AMX / AVX512-BF16; auto: bf16 for "
                        "4 or more frustums where the CPU has AMX)")
    d.add_argument("--workers", type=ca.int_at_least(1), default=2,
                   help="threads the network splits a frame's frustums over, >= 1 (default 2)")
    d.add_argument("--proposals", choices=("geometric", "external"), default=None,
                   help="2D proposal source (default: external when --detections2d is given)")
    d.add_argument("--classifier", type=ca.path_text, default=None, metavar="PATH|none",
                   help="proposal classifier for built-in proposals (default: the packaged one; none = off)")
    d.add_argument("--no-refine", action="store_true", help="no class-given second pass for built-in proposals")
    d.add_argument("--detector", metavar="MODULE:CALLABLE", help="use another detector factory (tests, plugins)")
    s = p.add_argument_group("frames")
    s.add_argument("--slop", type=ca.seconds, default=0.02, help="synchroniser slop, seconds >= 0 (default 0.02)")
    s.add_argument("--queue-size", type=ca.int_at_least(1), default=30,
                   help="synchroniser queue size per topic, >= 1 (default 30)")
    s.add_argument("--depth-scale", type=ca.depth_scale, default=None,
                   help="metres per raw depth unit, > 0 (default: by encoding, 16UC1 = 0.001)")
    s.add_argument("--up", type=ca.up_vector, help="fixed gravity-up vector in the camera optical frame, e.g. 0,-1,0")
    s.add_argument("--size-mismatch", choices=("rescale", "skip"), default="rescale")
    s.add_argument("--no-detections", action="store_true", help="do not write the Detection3DArray topic")
    s.add_argument("--no-copy", action="store_true", help="write only the detector's topics, not the input")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    pl = p.add_argument_group("live playback (--play)")
    pl.add_argument("--play", action="store_true", help="publish the bag's topics live instead")
    pl.add_argument("--rate", type=ca.rate, default=1.0, help="playback rate factor (<= 0: as fast as possible)")
    pl.add_argument("--topics", nargs="+", type=ca.topic, help="publish only these topics")
    pl.add_argument("--remap", nargs="+", type=ca.remap, default=[], metavar="FROM:=TO",
                    help="publish topic FROM as TO")
    pl.add_argument("--restamp", action="store_true", help="map header stamps to wall-clock time")
    pl.add_argument("--loop", action="store_true", help="play again and again")
    pl.add_argument("--clock", action="store_true", help="also publish /clock")
    pl.add_argument("--wait-subscribers", type=ca.seconds, default=0.0, metavar="SEC",
                    help="wait up to SEC (>= 0) seconds for subscribers before playing (all topics, or some "
                         "and no new ones for 1 s)")
    pl.add_argument("--delay", type=ca.seconds, default=0.0, help="seconds (>= 0) to wait before playing")


def _main_play(args: argparse.Namespace) -> int:
    remap = dict(args.remap)
    import rclpy

    rclpy.init()
    try:
        summary = play_bag(
            args.bag, args.rate, topics=args.topics, remap=remap, restamp=args.restamp, loop=args.loop,
            clock=args.clock, wait_subscribers=args.wait_subscribers, start_delay=args.delay,
            log=lambda s: print(s, file=sys.stderr),
        )
    except KeyboardInterrupt:
        return 130
    except (FileNotFoundError, ValueError, BagReadError) as e:
        print(f"replay --play: {e}", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - e.g. the context shut down by Ctrl-C mid-publish
        if not rclpy.ok():
            return 130
        print(f"replay --play: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        rclpy.try_shutdown()
    per = ", ".join(f"{t} {n}" for t, n in sorted(summary.per_topic.items()))
    print(f"played {summary.published} messages in {summary.wall_s:.2f} s ({per})")
    if summary.error:
        print(f"replay --play: {summary.error}", file=sys.stderr)
        return 1
    return 0


def main(args: argparse.Namespace) -> int:
    """Exit status: see :mod:`shape_detector.bags.replay_cli` (0, 1, 2, 3, 130, 143)."""
    if args.play:
        return _main_play(args)
    if not args.out:
        print("shape-detector replay: -o/--out OUT is required (or use --play)", file=sys.stderr)
        return 2
    from .bags.replay_cli import run_offline

    return run_offline(args, make_detector, replay_bag)


__all__ = ["MARKERS_TOPIC", "DETECTIONS_TOPIC", "PlaySummary", "ReplaySummary", "make_detector", "play_bag", "replay_bag"]
