"""``replay --play``: publish a bag's topics live with rclpy (where ``ros2 bag play`` is missing).

Messages go out at real or scaled rate, optionally re-stamped to the current time, so a running
``detector_node`` can be fed from a bag. ROS 1 bags are converted to ROS 2 messages on the fly.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable

from .ros1 import convert_message
from .source import BagReadError, BagSource, open_bag


@dataclass
class PlaySummary:
    """What a playback did: messages published (per topic), topics not published and why."""

    published: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0
    error: str | None = None


def _msg_class(msgtype: str) -> Any:
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def restamp(msg: Any, mapping: Callable[[int], int]) -> bool:
    """Shift ``msg.header.stamp`` (and nested Detection headers) through ``mapping`` (ns -> ns)."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None or not hasattr(stamp, "sec"):
        return False
    ns = mapping(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec))
    stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)
    for det in getattr(msg, "detections", []) or []:
        restamp(det, mapping)
    return True


def _publishers(node: Any, source: BagSource, topics: list[str] | None, remap: dict[str, str], qos_depth: int,
                summary: PlaySummary) -> dict[str, tuple[Any, str]]:
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    wanted = [t for t in source.topics if topics is None or t in topics]
    if topics:
        missing = [t for t in topics if t not in source.topics]
        if missing:
            raise ValueError(f"topics not in the bag: {missing}; bag topics: {sorted(source.topics)}")
    qos = QoSProfile(depth=qos_depth, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
    pubs: dict[str, tuple[Any, str]] = {}
    for t in wanted:
        msgtype = source.topics[t]
        try:
            cls = _msg_class(msgtype)
        except (ImportError, AttributeError, ValueError) as e:
            summary.skipped_topics[t] = f"no Python message class for {msgtype} ({e})"
            continue
        pubs[t] = (node.create_publisher(cls, remap.get(t, t), qos), msgtype)
    return pubs


def _wait_for_subscribers(pubs: dict[str, tuple[Any, str]], timeout_s: float, remap: dict[str, str],
                          log: Callable[[str], Any]) -> None:
    """Until every topic has a subscriber, or some have and that set has been stable for a
    second (topics nobody listens to do not hold playback up), at most ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
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
        log(f"play: no subscribers after {timeout_s:.1f} s")
    elif lonely:
        log(f"play: no subscribers on {', '.join(remap.get(t, t) for t in lonely)}")
    time.sleep(0.3)  # let the subscribers' side of discovery settle too


@dataclass
class _PlayOptions:
    rate: float
    restamp: bool
    clock_pub: Any
    should_stop: Any
    context: Any


def _payload(src: BagSource, m: Any, msgtype: str, opts: _PlayOptions, mapping: Callable[[int], int], jazzy: Any,
             summary: PlaySummary) -> bytes | None:
    """The CDR bytes to publish (converted from ROS 1, re-stamped); None to skip the message."""
    if not (opts.restamp or src.is_ros1):
        return bytes(m.raw)
    try:
        msg = src.deserialize(m.raw, msgtype)
        if src.is_ros1:
            msg = convert_message(msg, msgtype, jazzy)
        if opts.restamp:
            restamp(msg, mapping)
        return bytes(jazzy.serialize_cdr(msg, msgtype))
    except BagReadError:
        raise
    except Exception as e:  # noqa: BLE001
        if src.is_ros1:
            summary.skipped_topics.setdefault(m.topic, f"conversion failed: {e}")
            return None
        return bytes(m.raw)


def _play_once(src: BagSource, pubs: dict[str, tuple[Any, str]], opts: _PlayOptions, jazzy: Any,
               summary: PlaySummary) -> bool:
    """One pass over the bag; False when stopped (signal, rclpy shut down)."""
    import rclpy

    bag_start: int | None = None
    wall0 = 0.0
    wall0_ns = 0
    rate = opts.rate
    for m in src.messages(list(pubs)):
        if (opts.should_stop is not None and opts.should_stop()) or not rclpy.ok(context=opts.context):
            return False
        if bag_start is None:
            bag_start, wall0, wall0_ns = m.log_time_ns, time.perf_counter(), time.time_ns()
        if rate > 0:
            delay = wall0 + (m.log_time_ns - bag_start) / 1e9 / rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)

            def mapping(ns: int, _b: int = bag_start, _w: int = wall0_ns) -> int:
                return _w + int((ns - _b) / rate)
        else:  # as fast as possible: stamps follow the publish time

            def mapping(ns: int, _now: int = time.time_ns(), _log: int = m.log_time_ns) -> int:
                return _now + (ns - _log)
        pub, msgtype = pubs[m.topic]
        data = _payload(src, m, msgtype, opts, mapping, jazzy, summary)
        if data is None:
            continue
        if opts.clock_pub is not None:
            from rosgraph_msgs.msg import Clock

            ns = mapping(m.log_time_ns) if opts.restamp else m.log_time_ns
            c = Clock()
            c.clock.sec, c.clock.nanosec = divmod(ns, 1_000_000_000)
            opts.clock_pub.publish(c)
        pub.publish(data)
        summary.published += 1
        summary.per_topic[m.topic] = summary.per_topic.get(m.topic, 0) + 1
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
    """Publish a bag's messages with rclpy at ``rate`` x real time (``rate <= 0``: as fast as possible).

    ``topics``: only these (default all); ``remap``: ``{bag_topic: published_topic}``; ``restamp``:
    header stamps mapped to wall time (``now + (stamp - bag_start) / rate``; equal stamps stay equal;
    with ``rate <= 0`` publish time + (stamp - log time)) - needed to measure latency or for consumers
    that compare stamps with their clock; ``clock``: also publish ``/clock`` (bag or restamped time);
    ``wait_subscribers``: wait up to this many seconds until every published topic has a subscriber
    (or some have, unchanged for 1 s); ``loop``: repeat until interrupted. rclpy must be initialised
    in ``context`` (default: the global context; initialised and shut down here if needed).
    """
    import rclpy

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
        with open_bag(path) as source:
            for d in source.damage:
                log(f"play: damaged chunk, not published: {d}")
            pubs = _publishers(node, source, topics, remap, qos_depth, summary)
            for t, why in summary.skipped_topics.items():
                log(f"play: not publishing {t}: {why}")
            clock_pub = None
            if clock:
                from rosgraph_msgs.msg import Clock

                clock_pub = node.create_publisher(Clock, "/clock", 10)
            if wait_subscribers > 0:
                _wait_for_subscribers(pubs, wait_subscribers, remap, log)
            if start_delay > 0:
                time.sleep(start_delay)
            opts = _PlayOptions(rate, restamp, clock_pub, should_stop, context)
            src = source
            while True:
                try:
                    if not _play_once(src, pubs, opts, jazzy, summary):
                        return summary
                except BagReadError as e:
                    summary.error = str(e)
                    log(f"play: {e}")
                    return summary
                finally:
                    if src is not source:
                        src.close()
                if not loop:
                    break
                src = open_bag(path)
            time.sleep(0.2)  # let the last messages leave before the publishers go
    finally:
        summary.wall_s = time.perf_counter() - t_start
        node.destroy_node()
        if own_init:
            rclpy.try_shutdown()
    return summary
