"""Test-wide settings: ROS traffic stays on loopback / shared memory, one domain per run."""

from __future__ import annotations

import os
import random
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Set before anything imports rclpy; subprocesses inherit them.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(100, 200)))
# Fast DDS 2.x (Jazzy) reads FASTRTPS_DEFAULT_PROFILES_FILE, 3.x (Kilted) FASTDDS_DEFAULT_PROFILES_FILE
_PROFILE = str(ROOT / "shape_detector" / "config" / "fastdds_shm.xml")
os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = _PROFILE
os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = _PROFILE
os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "1")


@pytest.fixture(scope="session")
def sample_bag() -> Path:
    """The committed sample bag (rosbag2, MCAP storage)."""
    return ROOT / "bags" / "sample"


@pytest.fixture(scope="session")
def ros_context():
    """An initialised rclpy context for the session (shut down at the end)."""
    rclpy = pytest.importorskip("rclpy")
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


@pytest.fixture(autouse=True)
def _one_torch_thread(request):
    """One torch intra-op thread for tests that use torch: on a shared 2-core machine,
    oversubscribed OpenMP threads make small ops 20x slower. Restored afterwards."""
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(params=["rclpy", "rosbags"])
def types(request):
    """msg_conversion's message classes of each flavour: rclpy's and rosbags' (Jazzy store).
    The rclpy flavour is skipped when the module's ``RCLPY_MSGS`` package (default
    sensor_msgs) is not installed."""
    from msg_conversion.msgtypes import rclpy_types, rosbags_types

    if request.param == "rclpy":
        pytest.importorskip(getattr(request.module, "RCLPY_MSGS", "sensor_msgs") + ".msg")
        return rclpy_types()
    return rosbags_types()
