"""Negative evidence: a removed object disappears once its space is seen empty; an object
out of view or hidden behind another stays."""

from __future__ import annotations

import numpy as np

from shape_detector.scene import SceneMap
from shape_detector.scene.visibility import seen_empty, seen_empty_many
from test_scene_support import K, detection, pose, render, room

T0 = pose(0.0, 0.0, 1.2, 0.0)
CHAIR = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)
PARTS = [(CHAIR[0], CHAIR[1], np.eye(3))]


def _mapped(T=T0) -> SceneMap:
    m = SceneMap()
    d = render(room([CHAIR]), T)
    for i in range(4):
        m.update([detection(*CHAIR, T)], T, d, K, stamp_ns=i)
    assert len(m.objects()) == 1
    return m


def test_seen_empty_classifies_present_removed_and_hidden():
    assert seen_empty(PARTS, T0, render(room([CHAIR]), T0), K) is False
    assert seen_empty(PARTS, T0, render(room(), T0), K) is True
    wall = ((1.5, 0.0, 1.0), (0.2, 3.0, 2.0), 0.0)
    assert seen_empty(PARTS, T0, render(room([wall]), T0), K) is False  # hidden: nothing known
    assert seen_empty(PARTS, pose(0.0, 0.0, 1.2, np.pi), render(room(), pose(0.0, 0.0, 1.2, np.pi)), K) is None


def test_seen_empty_many_answers_each_object_as_seen_empty_does():
    behind = [((-3.0, 0.0, 0.45), (0.5, 0.5, 0.9), np.eye(3))]  # behind the camera: not in view
    two = PARTS + [((2.0, 1.0, 0.3), (0.3, 0.3, 0.3), np.eye(3))]
    for scene in (room([CHAIR]), room()):
        d = render(scene, T0)
        many = seen_empty_many([PARTS, behind, [], two], T0, d, K)
        assert many == [seen_empty(PARTS, T0, d, K), None, None, seen_empty(two, T0, d, K)]
    assert seen_empty_many([PARTS], T0, render(room(), T0), K) == [True]


def test_removed_object_disappears_after_delete_misses_frames():
    m = _mapped()
    empty = render(room(), T0)
    for i in range(m.config.delete_misses - 1):
        m.update([], T0, empty, K, stamp_ns=10 + i)
        assert len(m.objects()) == 1, "kept until seen empty delete_misses times"
    m.update([], T0, empty, K, stamp_ns=20)
    assert m.objects() == []


def test_a_detection_resets_the_empty_count():
    m = _mapped()
    empty, full = render(room(), T0), render(room([CHAIR]), T0)
    for i in range(10):  # every other frame empty: never delete_misses in a row
        if i % 2:
            m.update([detection(*CHAIR, T0)], T0, full, K, stamp_ns=10 + i)
        else:
            m.update([], T0, empty, K, stamp_ns=10 + i)
    assert len(m.objects()) == 1


def test_missed_detections_of_a_visible_object_do_not_delete_it():
    m = _mapped()
    full = render(room([CHAIR]), T0)
    for i in range(10):
        m.update([], T0, full, K, stamp_ns=10 + i)
    assert len(m.objects()) == 1


def test_out_of_view_object_stays():
    m = _mapped()
    away = pose(0.0, 0.0, 1.2, np.pi)  # turned around: the chair is behind the camera
    for i in range(10):
        m.update([], away, render(room(), away), K, stamp_ns=10 + i)
    assert len(m.objects()) == 1


def test_hidden_object_stays():
    m = _mapped()
    screen = ((1.5, 0.0, 1.0), (0.2, 3.0, 2.0), 0.0)
    d = render(room([screen]), T0)  # the chair is gone, but a screen in front hides its place
    for i in range(10):
        m.update([], T0, d, K, stamp_ns=10 + i)
    assert len(m.objects()) == 1


def test_out_of_range_object_stays():
    m = _mapped()
    far = pose(-4.0, 0.0, 1.2, 0.0)  # 7 m away: beyond the range trusted for free space
    for i in range(10):
        m.update([], far, render(room(), far), K, stamp_ns=10 + i)
    assert len(m.objects()) == 1
