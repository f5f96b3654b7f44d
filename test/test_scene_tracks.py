"""Scene map tracking: association, confirmation, class evidence, merging, static camera."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from shape_detector.classes import CLASSES
from shape_detector.scene import SceneConfig, SceneMap
from shape_detector.scene.observe import to_observation, upright_box
from test_scene_support import K, detection, pose, render, room

T0 = pose(0.0, 0.0, 1.2, 0.0)
CHAIR = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)
TABLE = ((3.0, 1.5, 0.375), (1.2, 0.8, 0.75), 0.3)


def _feed(m: SceneMap, dets_per_frame, T=T0, depth=None):
    for i, dets in enumerate(dets_per_frame):
        m.update(dets, T, depth, K if depth is not None else None, stamp_ns=1000 + i)


def test_confirmation_and_stable_id():
    m = SceneMap()
    det = detection(*CHAIR, T0)
    _feed(m, [[det]] * 2)
    assert m.objects() == []  # not yet confirmed
    _feed(m, [[det]] * 3)
    objs = m.objects()
    assert len(objs) == 1
    o = objs[0]
    assert o.id == 1 and o.class_name == "chair" and o.observations == 5
    np.testing.assert_allclose(o.center, CHAIR[0], atol=1e-6)
    np.testing.assert_allclose(o.size, CHAIR[1], atol=1e-6)
    np.testing.assert_allclose(o.rotation[:, 2], [0, 0, 1], atol=1e-9)
    assert 0.0 < o.score <= 1.0


def test_one_frame_false_positive_is_never_published():
    m = SceneMap()
    chair = detection(*CHAIR, T0)
    ghost = detection((2.0, -1.5, 0.4), (0.5, 0.5, 0.8), 0.0, T0, cls="toilet")
    frames = [[chair], [chair, ghost], [chair], [chair], [chair], [chair]]
    for i, dets in enumerate(frames):
        m.update(dets, T0, None, None, stamp_ns=i)
        assert all(o.class_name == "chair" for o in m.objects())
    assert len(m.objects()) == 1


def test_a_doubtful_track_is_kept_but_not_published_until_its_score_reaches_publish_score():
    weak = detection(*CHAIR, T0, score=0.45)  # the track's score never exceeds its detections' mean
    m = SceneMap()
    _feed(m, [[weak]] * 10)
    assert m.objects() == [] and not (m.grid().data == 100).any()
    assert len(m.tracks) == 1 and m.tracks[0].confirmed  # tracked, so later detections build on it
    _feed(m, [[detection(*CHAIR, T0, score=0.95)]] * 10)
    assert [o.class_name for o in m.objects()] == ["chair"] and (m.grid().data == 100).any()
    every = SceneMap(SceneConfig(publish_score=0.0))
    _feed(every, [[weak]] * 10)
    assert len(every.objects()) == 1


def test_score_grows_with_consistent_observations():
    m = SceneMap()
    det = detection(*CHAIR, T0, score=0.8)
    scores = []
    for i in range(8):
        m.update([det], T0, None, None, stamp_ns=i)
        scores += [o.score for o in m.objects()]
    assert len(scores) >= 4 and all(b >= a - 1e-12 for a, b in zip(scores, scores[1:]))
    assert scores[-1] > scores[0]


def test_one_frame_class_flip_keeps_track_and_class():
    m = SceneMap()
    chair = detection(*CHAIR, T0, cls="chair")
    flipped = detection(*CHAIR, T0, cls="toilet", score=0.9)
    _feed(m, [[chair]] * 4 + [[flipped]] + [[chair]] * 2)
    objs = m.objects()
    assert len(objs) == 1 and objs[0].class_name == "chair" and objs[0].observations == 7


def test_class_decided_by_accumulated_evidence_not_last_label():
    m = SceneMap(SceneConfig(track_classifier=""))  # the evidence alone (the track classifier has its own tests)
    p_desk = np.full(len(CLASSES), 0.01)
    p_desk[CLASSES.index("desk")] = 0.6
    p_desk[CLASSES.index("table")] = 0.3
    desk = detection(*TABLE, T0, cls="desk")
    desk.class_scores = p_desk
    table = detection(*TABLE, T0, cls="table")
    _feed(m, [[desk]] * 5 + [[table]])
    assert [o.class_name for o in m.objects()] == ["desk"]


def test_two_objects_side_by_side_keep_their_tracks():
    m = SceneMap()
    a = detection((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0, T0)
    b = detection((3.0, 0.65, 0.45), (0.5, 0.5, 0.9), 0.0, T0)
    _feed(m, [[a, b]] * 4)
    objs = m.objects()
    assert len(objs) == 2
    assert {round(o.center[1], 2) for o in objs} == {0.0, 0.65}


def test_noisy_boxes_fuse_to_the_truth_and_a_second_box_is_no_new_track():
    rng = np.random.default_rng(0)
    m = SceneMap()
    for i in range(20):
        c = np.asarray(CHAIR[0]) + rng.normal(0, 0.05, 3) * [1, 1, 0.2]
        dets = [detection(c, CHAIR[1], rng.normal(0, 0.05), T0, score=0.97)]
        if i % 4 == 0:  # the detector boxes the chair twice, the second box half inside the first
            dets.append(detection(c + [0.0, 0.12, 0.0], (0.45, 0.4, 0.85), 0.0, T0, score=0.6))
        m.update(dets, T0, None, None, stamp_ns=i)
    objs = m.objects()
    assert len(objs) == 1
    assert np.linalg.norm(objs[0].center[:2] - np.asarray(CHAIR[0][:2])) < 0.05


def test_duplicate_tracks_merge():
    m = SceneMap(SceneConfig(gate=0.05))  # a tiny gate makes the two offset boxes start two tracks
    a = detection((3.0, 0.0, 0.45), (0.6, 0.6, 0.9), 0.0, T0)
    b = detection((3.08, 0.05, 0.45), (0.6, 0.6, 0.9), 0.0, T0)
    _feed(m, [[a]] * 3 + [[b]] * 3)
    assert len(m.objects()) == 1 and m.objects()[0].id == 1


def test_a_displaced_duplicate_is_dropped_once_the_object_has_a_strong_track():
    # early views place the chair 38 cm to the side (a confirmed but weak track), later ones
    # where it stands: the first track overlaps the second in part (IoU ~0.14) and holds a
    # tenth of its weight, so it is a displaced duplicate, not a second chair
    there = detection(*CHAIR, T0, score=0.95)
    for config, early_class, kept in ((SceneConfig(), "chair", {2}),
                                      (SceneConfig(displaced_iou=0.0), "chair", {1, 2}),
                                      (SceneConfig(), "table", {1, 2})):  # another class: another object
        m = SceneMap(config)
        early = detection((3.0, 0.38, 0.45), (0.5, 0.5, 0.9), 0.0, T0, cls=early_class, score=0.8)
        _feed(m, [[early]] * 4)
        assert [o.id for o in m.objects()] == [1]
        _feed(m, [[there]] * 12)
        assert {o.id for o in m.objects()} == kept, (config.displaced_iou, early_class)


def test_quarter_turned_box_is_the_same_box():
    m = SceneMap()
    a = detection((3.0, 1.5, 0.375), (1.2, 0.8, 0.75), 0.0, T0, cls="table")
    b = detection((3.0, 1.5, 0.375), (0.8, 1.2, 0.75), np.pi / 2, T0, cls="table")
    _feed(m, [[a], [b], [a], [b]])
    o = m.objects()[0]
    np.testing.assert_allclose(o.size, [1.2, 0.8, 0.75], atol=1e-6)
    assert abs(np.sin(o.yaw)) < 1e-6


def test_face_spread_measures_where_the_detections_disagree():
    m = SceneMap()
    for i in range(40):  # the -x face always at 2.4 m, the +x face at 3.6 or 3.8 m
        far = 3.6 if i % 2 else 3.8
        m.update([detection(((2.4 + far) / 2, 1.5, 0.375), (far - 2.4, 0.8, 0.75), 0.0, T0, cls="table")],
                 T0, None, None, stamp_ns=i)
    sd = m.objects()[0].face_sd
    assert sd[0] < 0.01 and 0.07 < sd[1] < 0.13  # the spread of {3.6, 3.8} is 0.1 m
    assert sd[2] < 0.01 and sd[3] < 0.01


def test_face_spread_of_quarter_turns_and_merged_tracks():
    m = SceneMap()
    a = detection((3.0, 1.5, 0.375), (1.2, 0.8, 0.75), 0.0, T0, cls="table")
    b = detection((3.0, 1.5, 0.375), (0.8, 1.2, 0.75), np.pi / 2, T0, cls="table")
    _feed(m, [[a], [b], [a], [b]])
    np.testing.assert_allclose(m.objects()[0].face_sd, 0.0, atol=1e-9)  # the same box, turned
    m = SceneMap(SceneConfig(gate=0.05))  # two tracks at first, merged once both are confirmed
    c = detection((3.08, 0.05, 0.45), (0.6, 0.6, 0.9), 0.0, T0)
    _feed(m, [[detection((3.0, 0.0, 0.45), (0.6, 0.6, 0.9), 0.0, T0)]] * 3 + [[c]] * 3)
    (o,) = m.objects()
    assert np.all(o.face_sd > 0.01) and np.all(o.face_sd < 0.08)  # 8 / 5 cm apart, pooled


def test_primitives_follow_to_the_world():
    m = SceneMap()
    seat = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.05))
    legs = ((3.2, 0.2, 0.21), (0.04, 0.04, 0.42))
    det = detection(*CHAIR, T0, parts=[seat, legs])
    _feed(m, [[det]] * 3)
    prims = m.objects()[0].primitives
    assert len(prims) == 2
    centres = sorted(tuple(np.round(p.center, 6)) for p in prims)
    np.testing.assert_allclose(centres, sorted([seat[0], legs[0]]), atol=1e-6)
    np.testing.assert_allclose(sorted(tuple(np.round(p.size, 6)) for p in prims),
                               sorted([seat[1], legs[1]]), atol=1e-6)


def test_malformed_detections_are_skipped():
    m = SceneMap()
    bad = detection(*CHAIR, T0)
    bad.size = np.array([np.nan, 0.5, 0.9])
    neg = detection(*CHAIR, T0)
    neg.size = np.array([0.5, -0.5, 0.9])
    unknown = detection(*CHAIR, T0, cls="lamp")
    _feed(m, [[bad, neg, unknown]] * 4)
    assert m.objects() == [] and m.tracks == []
    with pytest.raises(ValueError, match="4x4"):
        m.update([], np.eye(3), None, None, 0)


def test_static_camera_mode_says_so_once_and_puts_z_up():
    m = SceneMap()
    up_cam = T0[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # (0, -1, 0) for this level camera
    det = detection(*CHAIR, T0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for i in range(4):
            m.update([det], None, None, None, stamp_ns=i, up_camera=up_cam)
    assert sum("static camera" in str(w.message) for w in caught) == 1
    o = m.objects()[0]
    np.testing.assert_allclose(o.size, CHAIR[1], atol=1e-6)
    # world = camera frame turned so that z is up, origin at the camera: 1.2 m above the chair's centre
    assert abs(o.center[2] - (CHAIR[0][2] - 1.2)) < 1e-6
    assert abs(np.linalg.norm(o.center[:2]) - 3.0) < 1e-6


def test_upright_box_finds_the_vertical_axis():
    R = np.stack([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]], axis=1)  # columns: x = up, y = world x, z = world y
    size, yaw, _ = upright_box(np.zeros(3), np.array([0.9, 0.5, 0.4]), R)
    np.testing.assert_allclose(size, [0.5, 0.4, 0.9])
    assert abs(yaw) < 1e-9


def test_observation_weight_prefers_sure_unclipped_boxes():
    sure = to_observation(detection(*CHAIR, T0, score=0.99), T0, 0, K, (120, 160))
    unsure = to_observation(detection(*CHAIR, T0, score=0.7), T0, 0, K, (120, 160))
    clipped = to_observation(detection((3.0, -1.9, 0.45), (0.5, 0.5, 0.9), 0.0, T0, score=0.99), T0, 0, K, (120, 160))
    assert sure.weight > 5 * unsure.weight
    assert sure.weight > clipped.weight


def test_depth_of_the_room_does_not_disturb_tracking():
    d = render(room([CHAIR]), T0)
    m = SceneMap()
    _feed(m, [[detection(*CHAIR, T0)]] * 5, depth=d)
    assert len(m.objects()) == 1


def test_depth_in_millimetres_and_bad_depth(caplog):
    d = render(room([CHAIR]), T0)
    mm = np.nan_to_num(d * 1000.0, nan=0.0).astype(np.uint16)
    a, b = SceneMap(), SceneMap()
    c = SceneMap(SceneConfig(camera_path_radius=0.0))  # only the depth could mark the floor free
    for i in range(4):
        a.update([detection(*CHAIR, T0)], T0, d, K, stamp_ns=i)
        b.update([detection(*CHAIR, T0)], T0, mm, K, stamp_ns=i)
        c.update([detection(*CHAIR, T0)], T0, d[None], K, stamp_ns=i)  # not 2D: depth skipped, logged
    assert abs(a.floor_z - b.floor_z) < 0.01
    assert (a.grid().data == 0).sum() == pytest.approx((b.grid().data == 0).sum(), rel=0.05)
    assert len(c.objects()) == 1 and (c.grid().data == 0).sum() == 0
    assert "depth not used" in caplog.text


def test_visible_share_counts_truncation_and_occlusion():
    from shape_detector.scene.observe import visible_share

    det = detection(*CHAIR, T0)
    free = render(room([CHAIR]), T0)
    half_hidden = render(room([CHAIR, ((1.5, 0.3, 1.0), (0.1, 0.6, 2.0), 0.0)]), T0)  # a post in front
    full = visible_share(det.center, det.size, det.rotation, K, 160, 120, depth=free)
    part = visible_share(det.center, det.size, det.rotation, K, 160, 120, depth=half_hidden)
    assert full == pytest.approx(1.0)
    assert 0.2 < part < 0.8
    cut = detection((3.0, -2.1, 0.45), (0.5, 0.5, 0.9), 0.0, T0)  # across the image's right border
    assert 0.0 < visible_share(cut.center, cut.size, cut.rotation, K, 160, 120) < 1.0
