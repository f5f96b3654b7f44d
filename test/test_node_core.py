"""The node's state and callbacks without ROS (NodeCore under a fake host): parameter
changes refused with the reason or taken into use, gravity up, warnings once per problem,
the periodic report, input callbacks that never raise."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from shape_detector.node_core import NodeCore
from shape_detector.node_params import PARAMETERS, descriptor_fields

pytestmark = pytest.mark.timeout(30)


class Det:
    score_threshold = 0.3


class Core(NodeCore):
    def __init__(self, **p):
        values = {k: v.default for k, v in PARAMETERS.items()}
        values.update(p)
        self.lines = []
        self.imu_subscribed = 0
        self.init_core(values, external=False)
        self.detector = Det()

    def log(self, level, text):
        self.lines.append((level, text))

    def subscribe_imu(self):
        self.imu_subscribed += 1
        self._imu_sub = object()


def test_invalid_changes_are_refused_with_the_reason_and_nothing_applied():
    c = Core()
    reason = c.set_parameters_checked([("sync_slop", 0.05), ("score_threshold", 2.0)])
    assert "score_threshold" in reason and c.p["sync_slop"] == PARAMETERS["sync_slop"].default


def test_valid_changes_reach_the_synchroniser_detector_and_imu():
    c = Core()
    assert c.set_parameters_checked([("sync_slop", 0.005), ("score_threshold", 0.6), ("up_source", "imu")]) is None
    assert c.sync.slop_ns == 5_000_000 and c.detector.score_threshold == pytest.approx(0.6)
    assert c.imu_subscribed == 1
    c.set_parameters_checked([("up_source", "fixed"), ("up_source", "imu")])
    assert c.imu_subscribed == 1  # subscribed once


def test_up_by_source():
    assert Core().current_up() is None
    assert Core(up_source="estimate").current_up() is None
    np.testing.assert_allclose(Core(up_source="fixed", up=[0.0, -2.0, 0.0]).current_up(), [0, -1, 0])
    c = Core(up_source="imu")
    assert c.current_up() is None and any("IMU" in t for _, t in c.lines)


def test_warnings_once_per_problem_then_rate_limited():
    c = Core()
    for k in range(5):
        c.warn("skip", f"frame {k} skipped: bad depth")
    c.warn("skip", "frame 9 skipped: other reason")
    assert [t for _, t in c.lines] == ["frame 0 skipped: bad depth", "frame 9 skipped: other reason"]


def test_bad_input_messages_are_counted_and_warned_not_raised():
    c = Core()
    c.on_input("image", 0, SimpleNamespace(data=b""))  # no header
    c.on_imu(SimpleNamespace())  # no linear_acceleration
    assert c.counters["received_image"] == 1 and c.counters["received_imu"] == 1
    assert len(c.lines) == 2 and all(level == "warning" for level, _ in c.lines)


def test_report_says_when_nothing_arrives():
    c = Core(stats_period=1.0)
    c._period_start -= 2.0
    c.maybe_report()
    assert any("no input yet" in t for _, t in c.lines)
    c.maybe_report(force=True)  # at exit: printed, never raises


def test_descriptor_fields_carry_ranges_and_choices():
    f = descriptor_fields(PARAMETERS["grid_resolution"])
    assert f["floating_point_range"] == (0.005, 1.0) and f["read_only"]
    f = descriptor_fields(PARAMETERS["pose_source"])
    assert "odom" in f["additional_constraints"] and "integer_range" not in f
    assert descriptor_fields(PARAMETERS["scene_delete_misses"])["integer_range"] == (1, 1000)


class Scene:
    """A scene feed whose camera pose gives gravity ``up`` (None: no pose at any stamp)."""

    def __init__(self, up):
        self.up, self.asked = up, []

    def up_at(self, frame_id, stamp_ns):
        self.asked.append((frame_id, stamp_ns))
        return None if self.up is None else np.asarray(self.up, dtype=np.float64)


def test_frame_up_takes_the_pose_with_auto_and_pose_and_says_when_pose_has_none():
    fs = SimpleNamespace(up=None)
    c = Core()  # the default is auto
    c.scene = Scene([0.0, -0.8, 0.6])
    np.testing.assert_allclose(c.frame_up(fs, 123, "cam"), [0.0, -0.8, 0.6])
    assert c.scene.asked == [("cam", 123)] and not c.lines
    c.scene = Scene(None)  # auto without a pose: estimated, silently (static camera mode is normal)
    assert c.frame_up(fs, 124, "cam") is None and not c.lines
    p = Core(up_source="pose")
    p.scene = Scene(None)
    assert p.frame_up(fs, 125, "cam") is None and any("up_source=pose" in t for _, t in p.lines)
    q = Core(up_source="pose", publish_scene=False)  # no scene feed at all
    assert q.frame_up(fs, 126, "cam") is None and any("publish_scene" in t for _, t in q.lines)


def test_frame_up_keeps_fixed_imu_and_estimate_choices():
    fixed = Core(up_source="fixed", up=[0.0, 0.0, 1.0])
    fixed.scene = Scene([0.0, -1.0, 0.0])
    np.testing.assert_allclose(fixed.frame_up(SimpleNamespace(up=fixed.current_up()), 1, "cam"), [0, 0, 1])
    est = Core(up_source="estimate")
    est.scene = Scene([0.0, -1.0, 0.0])
    assert est.frame_up(SimpleNamespace(up=None), 1, "cam") is None and not est.scene.asked
