"""Benchmark of the live node: ``detector_node`` in its own process, fed from a bag.

The bag is played (re-stamped to wall-clock time) into a ``detector_node`` subprocess;
a listener in this process records every ``~/markers`` message. Reported: frames/s of
marker output, latency from the image stamp (= its publish time) to the markers'
arrival, p50/p95, and how many frames were dropped because the node was busy.

    python -m shape_detector.node_bench [BAG] [--rate 1] [--loops 3] [--detector MOD:CALLABLE] [-p NAME:=VALUE]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_BAG = ROOT / "bags" / "sample"
FASTDDS_PROFILE = Path(__file__).resolve().parent / "config" / "fastdds_shm.xml"


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for ROS processes started from here: localhost discovery, shared-memory
    Fast DDS profile, a domain id (kept if already set)."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
    env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", env["FASTDDS_DEFAULT_PROFILES_FILE"])  # Fast DDS 2.x
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    else:
        env.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))
    env.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "1")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def node_command() -> list[str]:
    """``detector_node`` (console script next to this Python, or on PATH), else
    ``python -m shape_detector.node``."""
    for local in (Path(sys.executable).parent / "detector_node",
                  Path(sys.prefix) / "lib" / "shape_detector" / "detector_node"):
        if local.exists():
            return [str(local)]
    found = shutil.which("detector_node")
    if found:
        return [found]
    return [sys.executable, "-m", "shape_detector.node"]


def start_node(
    remaps: dict[str, str],
    params: dict[str, Any] | None = None,
    env: dict[str, str] | None = None,
    node_name: str | None = None,
    extra_pythonpath: list[str] | None = None,
    params_file: str | Path | None = None,
) -> subprocess.Popen:
    """Start ``detector_node`` with ``--ros-args`` remaps, a ``--params-file`` and ``-p``
    parameters (which win over the file); output (stdout + stderr) is piped."""
    cmd = node_command() + ["--ros-args"]
    if params_file:
        cmd += ["--params-file", str(params_file)]
    if node_name:
        cmd += ["-r", f"__node:={node_name}"]
    for a, b in remaps.items():
        cmd += ["-r", f"{a}:={b}"]
    for k, v in (params or {}).items():
        if isinstance(v, bool):
            v = "true" if v else "false"
        elif isinstance(v, (list, tuple)):
            v = "[" + ",".join(str(float(x)) for x in v) + "]"
        cmd += ["-p", f"{k}:={v}"]
    env = dict(env or ros_env())
    paths = [str(ROOT)] + list(extra_pythonpath or [])
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(paths)
    # its own process group: stop_node can end the node and anything it started at once
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    """``sig`` to ``proc``'s process group (its own, from start_node), else to ``proc``."""
    try:
        if os.getpgid(proc.pid) == proc.pid:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
    except (ProcessLookupError, PermissionError):
        pass


def stop_node(proc: subprocess.Popen, timeout: float = 10.0, sig: int = signal.SIGINT) -> int:
    """``sig`` (SIGINT), then SIGKILL to the process group after ``timeout`` s; always reaps
    the process (bounded: never waits more than ``timeout`` + 10 s). Returns the exit code
    (negative: killed by that signal)."""
    if proc.poll() is None:
        _signal_group(proc, sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pass
    # whatever the node left in its group (and the node itself if it did not stop)
    _signal_group(proc, signal.SIGKILL)
    try:
        proc.wait(timeout=10.0)
    except subprocess.TimeoutExpired:  # unkillable (D state): report instead of hanging
        return -9
    return int(proc.returncode)


class OutputCollector:
    """Reads a process' piped output on a thread; ``text`` is everything so far."""

    def __init__(self, proc: subprocess.Popen, echo: bool = False) -> None:
        self.lines: list[str] = []
        self._echo = echo
        self._t = threading.Thread(target=self._run, args=(proc,), daemon=True)
        self._t.start()

    def _run(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.append(line)
            if self._echo:
                sys.stderr.write(line)

    def wait_for(self, needle: str, timeout: float) -> bool:
        """True once ``needle`` appeared in the output within ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(needle in ln for ln in self.lines):
                return True
            time.sleep(0.05)
        return False

    @property
    def text(self) -> str:
        """The output so far."""
        return "".join(self.lines)


class MarkerListener:
    """Records ``(arrival_ns, stamp_ns, frame_id, n_markers)`` of every MarkerArray on
    ``topic``; spins its own executor thread."""

    def __init__(self, context: Any, topic: str = "/shape_detector/markers") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from visualization_msgs.msg import MarkerArray

        self.received: list[tuple[int, int, str, int]] = []
        self.node = rclpy.create_node(f"marker_listener_{os.getpid()}", context=context)
        self.node.create_subscription(
            MarkerArray, topic, self._cb, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        )
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._t = threading.Thread(target=self._spin, daemon=True)
        self._t.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - context shut down
            pass

    def _cb(self, msg: Any) -> None:
        now = time.time_ns()
        h = msg.markers[0].header if msg.markers else None
        stamp = h.stamp.sec * 1_000_000_000 + h.stamp.nanosec if h is not None else -1
        self.received.append((now, stamp, h.frame_id if h is not None else "", len(msg.markers)))

    def wait_quiet(self, expected: int, timeout: float, quiet: float = 1.5) -> None:
        """Until ``expected`` arrived, or nothing new for ``quiet`` s, or ``timeout``."""
        deadline = time.monotonic() + timeout
        last_n, last_change = len(self.received), time.monotonic()
        while time.monotonic() < deadline and len(self.received) < expected:
            time.sleep(0.05)
            if len(self.received) != last_n:
                last_n, last_change = len(self.received), time.monotonic()
            elif time.monotonic() - last_change > quiet:
                break

    def close(self) -> None:
        """Stop spinning, join the spin thread (bounded), destroy the node."""
        self.executor.shutdown(timeout_sec=1.0)
        self.executor.wake()
        self._t.join(timeout=5.0)
        self.node.destroy_node()


def _receive_stats(rec: list, sent: int, wall: float) -> dict[str, Any]:
    """Frame counts, output frames/s (between the first and last arrival), input frames/s over
    ``wall`` s and stamp->arrival latency p50 / p95 / max (ms) of the received
    ``(arrival ns, stamp ns, ...)`` tuples ``rec`` (stamp <= 0: unknown, no latency)."""
    arrivals = np.array([r[0] for r in rec], dtype=np.float64)
    lat = np.array([(r[0] - r[1]) / 1e6 for r in rec if r[1] > 0])
    fps = (len(rec) - 1) / ((arrivals[-1] - arrivals[0]) / 1e9) if len(rec) > 1 else 0.0
    return dict(
        frames_sent=sent,
        frames_received=len(rec),
        frames_dropped=sent - len(rec),
        fps=float(fps),
        input_fps=float(sent / wall) if wall > 0 else 0.0,
        latency_p50_ms=float(np.percentile(lat, 50)) if lat.size else float("nan"),
        latency_p95_ms=float(np.percentile(lat, 95)) if lat.size else float("nan"),
        latency_max_ms=float(lat.max()) if lat.size else float("nan"),
    )


def rss_mb(pid: int, children: bool = False) -> float:
    """Resident set size of process ``pid`` in MiB (Linux /proc), with ``children`` plus that of
    its descendants (the node's detector processes); NaN when unreadable."""
    try:
        total = 0.0
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                total = int(line.split()[1]) / 1024.0
        if children:
            for task in Path(f"/proc/{pid}/task").iterdir():
                for child in (task / "children").read_text().split():
                    total += rss_mb(int(child), True)
        return total
    except (OSError, ValueError):
        return float("nan")


def bench_node(
    bag: str | Path | None = None,
    weights: str | None = None,
    *,
    rate: float = 1.0,
    loops: int = 1,
    detector_factory: str | None = None,
    extra_pythonpath: list[str] | None = None,
    ready_timeout: float = 120.0,
    echo: bool = False,
    print_result: bool = True,
    node_params: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run ``detector_node`` on ``bag`` (default: the sample bag) played ``loops`` times at
    ``rate``, with ``node_params`` set on the node; returns and prints frames/s and
    stamp->markers latency p50/p95 (ms)."""
    import rclpy

    from .bags.source import open_bag
    from .bags.topics import select_topics
    from .replay import play_bag

    bag = Path(bag) if bag else DEFAULT_BAG
    with open_bag(bag) as src:
        sel = select_topics(src)
    remaps = {"image": sel.image, "depth": sel.depth, "camera_info": sel.camera_info}
    params: dict[str, Any] = {"stats_period": 5.0}
    if weights:
        params["weights"] = str(weights)
    if detector_factory:
        params["detector_factory"] = detector_factory
    params.update(node_params or {})
    env = ros_env()
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "FASTDDS_DEFAULT_PROFILES_FILE",
                                            "FASTRTPS_DEFAULT_PROFILES_FILE")})
    spawned_ns = time.time_ns()
    proc = start_node(remaps, params, env=env, extra_pythonpath=extra_pythonpath)
    out = OutputCollector(proc, echo=echo)
    ctx = rclpy.context.Context()
    rclpy.init(args=["node_bench"], context=ctx)  # not sys.argv: its -p NAME:=VALUE are the node's
    listener = MarkerListener(ctx)
    result: dict[str, Any] = {"bag": str(bag), "rate": rate, "loops": loops}
    try:
        if not out.wait_for("ready:", ready_timeout):
            raise RuntimeError(f"detector_node did not become ready in {ready_timeout} s:\n{out.text[-3000:]}")
        result["ready_s"] = (time.time_ns() - spawned_ns) / 1e9
        sent = 0
        t0 = time.perf_counter()
        for k in range(max(1, loops)):
            s = play_bag(bag, rate, restamp=True, context=ctx, wait_subscribers=30.0 if k == 0 else 0.0,
                         node_name=f"bench_player_{os.getpid()}_{k}", log=lambda *_: None)
            sent += s.per_topic.get(sel.image, 0)
        listener.wait_quiet(sent, timeout=60.0)
        wall = time.perf_counter() - t0
        result.update(_receive_stats(list(listener.received), sent, wall))
        if listener.received:  # from spawning the node to its first published frame (player included)
            result["first_frame_s"] = (listener.received[0][0] - spawned_ns) / 1e9
        result["node_rss_mb"] = rss_mb(proc.pid, children=True)
    finally:
        # the child first: whatever happens to this process' ROS teardown, it is reaped
        rc = stop_node(proc)
        result["node_exit_code"] = rc
        listener.close()
        rclpy.try_shutdown(context=ctx)
    if print_result:
        print(
            f"node: {result['frames_received']}/{result['frames_sent']} frames, {result['fps']:.2f} frames/s "
            f"(input {result['input_fps']:.2f}/s, rate {rate}), latency stamp->markers p50 "
            f"{result['latency_p50_ms']:.1f} ms, p95 {result['latency_p95_ms']:.1f} ms, "
            f"dropped {result['frames_dropped']}; ready {result['ready_s']:.2f} s and first frame "
            f"{result.get('first_frame_s', float('nan')):.2f} s after start, node RSS {result['node_rss_mb']:.0f} MiB (its detector processes included)",
            flush=True,
        )
    return result


def main(argv: list[str] | None = None) -> int:
    """``python -m shape_detector.node_bench``: the node benchmark from the command line."""
    p = argparse.ArgumentParser(prog="python -m shape_detector.node_bench", description=__doc__.split("\n\n")[0])
    p.add_argument("bag", nargs="?", default=None)
    p.add_argument("--weights")
    p.add_argument("--rate", type=float, default=1.0)
    p.add_argument("--loops", type=int, default=1)
    p.add_argument("--detector", help="detector factory MODULE:CALLABLE")
    p.add_argument("--echo", action="store_true", help="show the node's log")
    p.add_argument("--json", action="store_true")
    p.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                   help="a node parameter, as ros2 run's -p (e.g. -p pipeline:=false -p workers:=2)")
    a = p.parse_args(argv)
    node_params = {}
    for item in a.param:
        name, sep, value = item.partition(":=")
        if not sep:
            p.error(f"-p wants NAME:=VALUE, got {item!r}")
        node_params[name] = value
    res = bench_node(a.bag, a.weights, rate=a.rate, loops=a.loops, detector_factory=a.detector, echo=a.echo,
                     print_result=not a.json, node_params=node_params)
    if a.json:
        print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
