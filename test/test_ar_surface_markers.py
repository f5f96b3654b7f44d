"""Surfaces -> MarkerArray (both message flavours)."""

from __future__ import annotations

import numpy as np
from ar_scenes import bed, chair, table

from msg_conversion.surfaces import DELETEALL, LINE_STRIP, TEXT_VIEW_FACING, surfaces_to_markers
from shape_detector.ar import ArScene, surfaces

RCLPY_MSGS = "visualization_msgs"  # for conftest's ``types`` fixture


def test_outlines_and_labels(types) -> None:
    s = surfaces(ArScene([table(1, (0.0, 0.0)), chair(2, (2.0, 0.0)), bed(3, (4.0, 0.0))]))
    arr = surfaces_to_markers(s, types, stamp_ns=1_500_000_000, frame_id="odom")
    m = arr.markers
    assert m[0].action == DELETEALL and len(m) == 1 + 2 * len(s) == 7
    outlines = [x for x in m if x.ns == "surfaces"]
    labels = [x for x in m if x.ns == "surface_labels"]
    assert [x.type for x in outlines] == [LINE_STRIP] * 3 and [x.type for x in labels] == [TEXT_VIEW_FACING] * 3
    assert [x.text for x in labels] == ["place (table #1)", "sit (chair #2)", "lie (bed #3)"]
    first = outlines[0]
    assert first.header.frame_id == "odom" and first.header.stamp.sec == 1
    pts = np.array([[p.x, p.y, p.z] for p in first.points])
    assert len(pts) == 5 and np.allclose(pts[0], pts[-1])  # closed ring
    np.testing.assert_allclose(pts[:, 2], 0.76, atol=1e-9)
    np.testing.assert_allclose(np.sort(np.unique(np.round(pts[:, 0], 6))), [-0.5, 0.5])


def test_skips_bad_polygons(types) -> None:
    class Bad:
        object_id, class_name, height, affordance = 1, "table", 0.7, "place"
        polygon = np.array([[0.0, 0.0], [np.nan, 1.0], [1.0, 1.0]])

    arr = surfaces_to_markers([Bad()], types, 0, "odom")
    assert len(arr.markers) == 1
