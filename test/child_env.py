"""The environment of a child Python process that a test starts."""

from __future__ import annotations

import os
from pathlib import Path

TEST_DIR = Path(__file__).resolve().parent
ROOT = TEST_DIR.parent


def child_env(**extra: str) -> dict[str, str]:
    """``os.environ`` with the repository and the test folder put before the inherited
    ``PYTHONPATH`` (kept: in a sourced ROS workspace that is where rclpy and the messages
    live), plus ``extra``."""
    inherited = os.environ.get("PYTHONPATH", "")
    paths = [str(ROOT), str(TEST_DIR)] + ([inherited] if inherited else [])
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths), **extra}
