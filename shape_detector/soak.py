"""``shape-detector bench soak``: the live node under sustained overload.

``detector_node`` runs as a subprocess; this process publishes the sample bag's frames
(re-stamped to the current time) at ``rate_factor`` times the rate the node can process
(measured first, with the node saturated), for ``minutes``. Printed: the node's resident
memory (RSS) after minute 1 and at the end, frames offered, synchronised, processed,
dropped and published, whether every published frame came in stamp order, and the node's
exit code after SIGINT. Acceptance: RSS growth <= 10 %, exit code 0, all in order.

    shape-detector bench soak --minutes 10 --rate-factor 2
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path
from typing import Any

from .node_bench import DEFAULT_BAG, MarkerListener, OutputCollector, ros_env, rss_mb, start_node, stop_node

_TOTALS = re.compile(r"totals: (\d+) synced, (\d+) processed, (\d+) dropped")


def node_totals(log: str) -> tuple[int, int, int]:
    """(synced, processed, dropped) from the node's last statistics line; zeros if none."""
    found = _TOTALS.findall(log)
    return tuple(int(x) for x in found[-1]) if found else (0, 0, 0)  # type: ignore[return-value]


def in_stamp_order(stamps: list[int]) -> bool:
    """Whether ``stamps`` (ns) strictly increase."""
    return all(b > a for a, b in zip(stamps, stamps[1:]))


def _load_frames(bag: Path, types: Any, limit: int = 20) -> list[tuple[Any, Any, Any]]:
    """Up to ``limit`` (image, depth, camera_info) rclpy messages built from ``bag``."""
    from msg_conversion import K_to_camera_info, depth_to_image, numpy_to_image

    from .bags.reader import BagFrameReader

    out = []
    with BagFrameReader(bag, slop=0.02, queue_size=10) as reader:
        for f in reader.frames():
            pf = f.prepare()
            h, w = pf.depth.shape
            out.append((numpy_to_image(pf.rgb, "rgb8", types, 0, f.frame_id),
                        depth_to_image(pf.depth, types, "32FC1", 0, f.frame_id),
                        K_to_camera_info(pf.K, w, h, types, 0, f.frame_id)))
            if len(out) >= limit:
                break
    if not out:
        raise RuntimeError(f"no synchronised frames in {bag}")
    return out


class _Feeder:
    """Publishes the frames round-robin with strictly increasing current-time stamps."""

    def __init__(self, ctx: Any, frames: list, prefix: str) -> None:
        import rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from msg_conversion.msgtypes import rclpy_types

        T = rclpy_types()
        self.node = rclpy.create_node(f"soak_feeder_{os.getpid()}", context=ctx)
        qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs = [self.node.create_publisher(T.Image, f"{prefix}/image", qos),
                     self.node.create_publisher(T.Image, f"{prefix}/depth", qos),
                     self.node.create_publisher(T.CameraInfo, f"{prefix}/camera_info", qos)]
        self.frames = frames
        self.sent = 0
        self._last = 0

    def wait_subscribers(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() for p in self.pubs):
                return True
            time.sleep(0.05)
        return False

    def publish_one(self) -> None:
        stamp = max(time.time_ns(), self._last + 1)
        self._last = stamp
        msgs = self.frames[self.sent % len(self.frames)]
        for pub, msg in zip(self.pubs[::-1], msgs[::-1]):  # camera_info first
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            pub.publish(msg)
        self.sent += 1

    def run(self, rate_hz: float, seconds: float, every_s: float = 60.0, on_tick: Any = None) -> None:
        """Publish at ``rate_hz`` for ``seconds``; ``on_tick(elapsed_s)`` every ``every_s``."""
        t0 = time.monotonic()
        next_tick = every_s
        k = 0
        while (elapsed := time.monotonic() - t0) < seconds:
            if on_tick is not None and elapsed >= next_tick:
                on_tick(elapsed)
                next_tick += every_s
            self.publish_one()
            k += 1
            delay = t0 + k / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def close(self) -> None:
        self.node.destroy_node()


def soak(
    minutes: float = 10.0,
    rate_factor: float = 2.0,
    bag: str | Path | None = None,
    calibrate_s: float = 30.0,
    node_params: dict[str, Any] | None = None,
    echo: bool = False,
) -> dict[str, Any]:
    """Run the soak and return its numbers (RSS in MiB, counts in frames, rates in frames/s)."""
    import rclpy

    from msg_conversion.msgtypes import rclpy_types

    bag = Path(bag) if bag else DEFAULT_BAG
    prefix = f"/soak{os.getpid()}"
    params: dict[str, Any] = {"stats_period": 10.0, **(node_params or {})}
    env = ros_env()
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID",
                                            "FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")})
    frames = _load_frames(bag, rclpy_types())
    proc = start_node({t: f"{prefix}/{t}" for t in ("image", "depth", "camera_info")}, params, env=env)
    out = OutputCollector(proc, echo=echo)
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    listener = MarkerListener(ctx)
    feeder = _Feeder(ctx, frames, prefix)
    res: dict[str, Any] = {"minutes": minutes, "rate_factor": rate_factor, "pid": proc.pid}
    rss: list[tuple[float, float]] = []
    try:
        if not out.wait_for("ready:", 180.0):
            raise RuntimeError(f"detector_node not ready:\n{out.text[-3000:]}")
        feeder.wait_subscribers(30.0)
        # capacity: the node saturated (offered more than it can take), markers per second
        feeder.run(30.0, calibrate_s / 3)
        n1, t1 = len(listener.received), time.monotonic()
        feeder.run(30.0, calibrate_s * 2 / 3)
        capacity = (len(listener.received) - n1) / (time.monotonic() - t1)
        res["capacity_fps"] = capacity
        res["offered_fps"] = rate = max(0.5, rate_factor * capacity)
        sent0 = feeder.sent
        rss.append((0.0, rss_mb(proc.pid)))
        feeder.run(rate, minutes * 60.0, on_tick=lambda el: rss.append((el, rss_mb(proc.pid))))
        rss.append((minutes * 60.0, rss_mb(proc.pid)))
        res["frames_in"] = feeder.sent
        res["frames_in_soak"] = feeder.sent - sent0
        listener.wait_quiet(10**9, timeout=30.0, quiet=3.0)
    finally:
        # the child first: whatever happens to this process' ROS teardown, it is reaped
        res["node_exit_code"] = stop_node(proc, timeout=20.0)
        feeder.close()
        listener.close()
        rclpy.try_shutdown(context=ctx)
    return _summarise(res, rss, list(listener.received), out.text)


def _summarise(res: dict[str, Any], rss: list[tuple[float, float]], received: list, log: str) -> dict[str, Any]:
    """Add RSS, counts and the order check to ``res``."""
    synced, processed, dropped = node_totals(log)
    stamps = [r[1] for r in received]
    minute1 = next((v for t, v in rss if t >= 59.0), rss[-1][1])
    res.update(
        rss_mb_series=[(round(t), round(v, 1)) for t, v in rss],
        rss_mb_minute1=minute1,
        rss_mb_end=rss[-1][1],
        rss_growth=(rss[-1][1] - minute1) / minute1 if minute1 else float("nan"),
        synced=synced, processed=processed, dropped=dropped,
        published=len(received),
        in_order=in_stamp_order(stamps),
        traceback_in_log="Traceback" in log,
    )
    res["ok"] = bool(res["rss_growth"] <= 0.10 and res["in_order"] and res["node_exit_code"] == 0
                     and not res["traceback_in_log"])
    return res


def print_soak(res: dict[str, Any]) -> None:
    """The soak's numbers, one line each."""
    print(f"soak: {res['minutes']} min at {res['offered_fps']:.2f} frames/s offered "
          f"({res['rate_factor']}x the measured capacity {res['capacity_fps']:.2f} frames/s)")
    print(f"RSS: minute 1 {res['rss_mb_minute1']:.1f} MiB, end {res['rss_mb_end']:.1f} MiB, "
          f"growth {100 * res['rss_growth']:+.1f} %; per minute {res['rss_mb_series']}")
    print(f"frames: in {res['frames_in']}, synced {res['synced']}, processed {res['processed']}, "
          f"dropped {res['dropped']}, published {res['published']}")
    print(f"published in stamp order: {res['in_order']}; node exit code {res['node_exit_code']}; "
          f"traceback in log: {res['traceback_in_log']}")
    print("SOAK OK" if res["ok"] else "SOAK FAILED", flush=True)
