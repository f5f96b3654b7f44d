"""Geometric proposals on ray-cast toy scenes: touching furniture, chair legs, structure removal."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.proposals import Proposal, get_proposer
from shape_detector.proposals.evaluate import VGA_K, angle_deg, box_iou, evaluate_proposals
from shape_detector.proposals.geometric import GeometricConfig, GeometricProposer

from toy_scenes import box_part, chair_parts, toy_scene, up_from_pitch_roll

ROOM = [(np.pi / 2, 3.25), (0.0, 3.0), (np.pi, 3.0)]  # back wall 3.25 m ahead, side walls


def _best(props, box) -> tuple[float, tuple]:
    pb = np.array([p.box2d for p in props], np.float64).reshape(-1, 4)
    iou = box_iou(np.array([box], np.float64), pb)[0]
    k = int(np.argmax(iou))
    return float(iou[k]), tuple(pb[k])


@pytest.fixture(scope="module")
def touching():
    # a dresser and a night stand side by side, fronts flush, backs against the wall
    objs = [("dresser", [box_part(-0.3, 3.0, 1.0, 0.5, 1.1)]), ("night_stand", [box_part(0.45, 3.0, 0.5, 0.5, 0.6)])]
    return toy_scene(objs, up=up_from_pitch_roll(20.0, 2.0), walls=ROOM, seed=1)


def test_touching_boxes_give_separate_and_merged_proposals(touching):
    f = touching
    grav, props = GeometricProposer()(f.depth, f.K)  # geometry only (no RGB)
    assert grav.source == "floor" and angle_deg(grav.up, f.up) < 1.0
    assert all(isinstance(p, Proposal) and p.class_name is None and p.source == "geometric" for p in props)
    assert 2 <= len(props) <= 30
    for o in f.objects:
        iou, _ = _best(props, o.box2d)
        assert iou >= 0.75, (o.class_name, iou)
    b = np.array([o.box2d for o in f.objects])
    union = (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max())
    assert _best(props, union)[0] >= 0.9
    # boxes are pixel edges inside the image, scores in (0, 1]
    pb = np.array([p.box2d for p in props])
    assert (pb[:, 0] >= 0).all() and (pb[:, 2] <= 640).all() and (pb[:, 3] <= 480).all()
    assert (pb[:, 2] > pb[:, 0]).all() and (pb[:, 3] > pb[:, 1]).all()
    assert all(0.0 < p.score <= 1.0 for p in props)


def test_colour_separates_equal_height_neighbours():
    # two equal boxes touching side by side: no geometric cue, but different colours
    objs = [("dresser", [box_part(-0.4, 3.0, 0.8, 0.5, 0.9)]), ("dresser", [box_part(0.4, 3.0, 0.8, 0.5, 0.9)])]
    f = toy_scene(objs, up=up_from_pitch_roll(20.0, 0.0), walls=ROOM, seed=2)
    rgb = np.full((480, 640, 3), 200, np.uint8)
    rgb[f.instance_mask == 1] = (180, 40, 40)
    rgb[f.instance_mask == 2] = (40, 60, 170)
    _, props = GeometricProposer()(f.depth, f.K, rgb=rgb)
    for o in f.objects:
        assert _best(props, o.box2d)[0] >= 0.75


def test_chair_legs_stay_with_the_seat():
    up = up_from_pitch_roll(15.0, 0.0)
    f = toy_scene([("chair", chair_parts(0.2, 2.5, 0.5))], up=up, walls=[(np.pi / 2, 4.0)], seed=3)
    gt = f.objects[0].box2d
    _, props = GeometricProposer()(f.depth, f.K)
    iou, box = _best(props, gt)
    assert iou >= 0.9
    # the box reaches the feet of the legs (GT bottom = lowest leg pixel)
    assert abs(box[3] - gt[3]) <= 8 and abs(box[1] - gt[1]) <= 8


def test_chair_beside_a_table():
    objs = [("chair", chair_parts(0.2, 2.5, 0.5)), ("table", [box_part(-0.6, 3.0, 1.0, 0.8, 0.75)])]
    f = toy_scene(objs, up=up_from_pitch_roll(25.0, 0.0), walls=[(np.pi / 2, 4.0)], seed=4)
    _, props = GeometricProposer()(f.depth, f.K)
    for o in f.objects:
        assert _best(props, o.box2d)[0] >= 0.8, o.class_name


def test_floor_walls_removed_and_debug():
    stand = [("night_stand", [box_part(0.0, 2.6, 0.5, 0.45, 0.6)])]
    f = toy_scene(stand, up=up_from_pitch_roll(15.0, 0.0), walls=ROOM, seed=5)
    prop = GeometricProposer()
    grav, props = prop(f.depth, f.K)
    d = prop.debug
    assert len(d.walls) >= 1
    s = d.grid.stride
    inst = f.instance_mask[s // 2 :: s, s // 2 :: s]
    # floor and walls are not object points; (almost) all object points belong to the stand
    assert d.floor_mask[inst == 0].mean() > 0.3
    assert (inst[d.object_mask] == 1).mean() > 0.95
    assert _best(props, f.objects[0].box2d)[0] >= 0.85
    # nothing big (a wall or the floor) is proposed
    areas = [(p.box2d[2] - p.box2d[0]) * (p.box2d[3] - p.box2d[1]) for p in props]
    assert max(areas) < 0.25 * 640 * 480


def test_given_up_empty_and_degenerate_inputs():
    f = toy_scene([("table", [box_part(0.0, 3.0, 1.2, 0.8, 0.75)])], up=up_from_pitch_roll(10.0, 0.0), seed=6)
    up = np.asarray(f.up)
    grav, props = GeometricProposer()(f.depth, f.K, up=up * 3.0)
    np.testing.assert_allclose(grav.up, up / np.linalg.norm(up))
    assert grav.confidence == 1.0 and grav.floor_height == pytest.approx(1.3, abs=0.03)
    assert _best(props, f.objects[0].box2d)[0] >= 0.85
    grav, props = GeometricProposer()(np.full((480, 640), np.nan, np.float32), VGA_K)
    assert props == [] and grav.source == "prior" and grav.confidence == 0.0
    floor_only = toy_scene([], up=up_from_pitch_roll(20.0, 0.0), seed=7)
    assert GeometricProposer()(floor_only.depth, floor_only.K)[1] == []


def test_get_proposer_and_evaluate():
    p = get_proposer("geometric", stride=4, max_proposals=10)
    assert isinstance(p, GeometricProposer) and p.config.max_proposals == 10
    assert isinstance(get_proposer("geometric", config=GeometricConfig()), GeometricProposer)
    with pytest.raises(ValueError):
        get_proposer("nope")
    assert Proposal((1, 2, 3, 4), "chair", 0.5).as_tuple() == (1.0, 2.0, 3.0, 4.0, "chair")
    frames = [
        toy_scene([("table", [box_part(0.0, 3.0, 1.2, 0.8, 0.75)])], up=up_from_pitch_roll(12.0, 2.0), seed=8),
        toy_scene([("chair", chair_parts(-0.3, 2.4, 0.3))], up=up_from_pitch_roll(25.0, -3.0), walls=ROOM, seed=9),
    ]
    res = evaluate_proposals(frames, proposer=p)
    assert res["frames"] == 2 and res["objects"] == 2
    assert res["recall"] == 1.0
    assert res["up_err_median_deg"] < 1.0 and res["proposals_per_frame"] <= 10


def test_evaluate_keeps_the_best_k_and_counts_each_threshold_pair():
    frame = toy_scene([("table", [box_part(0.0, 3.0, 1.2, 0.8, 0.75)])], up=up_from_pitch_roll(12.0, 2.0), seed=8)
    (obj,) = frame.objects
    x1, y1, x2, y2 = obj.box2d
    shifted = (x1 + 0.1 * (x2 - x1), y1, x2 + 0.1 * (x2 - x1), y2)  # 2D IoU 0.82 with the object
    geometric = get_proposer("geometric", stride=4)

    def proposer(depth, K, up=None, rgb=None):
        grav, _ = geometric(depth, K, up=up, rgb=rgb)
        return grav, [Proposal(shifted, None, 0.4), Proposal((0, 0, 20, 20), None, 0.9)]

    pairs = [(0.0, 0.5), (0.0, 0.9)]
    one = evaluate_proposals([frame], proposer=proposer, top_k=1, recall_at=pairs)
    two = evaluate_proposals([frame], proposer=proposer, top_k=2, recall_at=pairs)
    assert one["recall"] == 0.0 and one["proposals_per_frame"] == 1  # the better-scored box misses
    assert two["recall"] == 1.0
    assert two["recall_table"] == {"visible>=0 iou>=0.5": [1.0, 1], "visible>=0 iou>=0.9": [0.0, 1]}


def test_rank_features_are_the_features_and_their_quadratic_terms():
    from shape_detector.proposals.geometric import KINDS, _RANK_W, rank_features

    rng = np.random.default_rng(0)
    F = rng.normal(size=(5, 2 + len(KINDS) + 9))  # bias, kinds, 9 geometry, consensus
    Q = rank_features(F)
    g = F[:, 1 + len(KINDS):]
    assert Q.shape == (5, F.shape[1] + g.shape[1] * (g.shape[1] + 1) // 2) == (5, len(_RANK_W))
    np.testing.assert_array_equal(Q[:, : F.shape[1]], F)
    assert Q[2, F.shape[1]] == pytest.approx(g[2, 0] ** 2)  # first product: the first geometry column squared
    assert Q[2, F.shape[1] + 1] == pytest.approx(g[2, 0] * g[2, 1])


def test_fitted_ranker_scores_matching_hypotheses_above_the_rest(touching):
    from shape_detector.proposals.evaluate import fit_ranker
    from shape_detector.proposals.geometric import rank_features

    chairs = toy_scene([("chair", chair_parts(-0.4, 2.4)), ("table", [box_part(0.5, 2.6, 1.0, 0.7, 0.75)])],
                       up=up_from_pitch_roll(15.0), walls=ROOM, seed=2)
    frames = [touching, chairs]
    w = fit_ranker(frames, lam=1e-2)
    assert w.shape == (75,) and np.all(np.isfinite(w))
    prop = GeometricProposer(GeometricConfig(max_proposals=1))
    pos, neg = [], []
    for f in frames:
        prop(f.depth, f.K)
        s = rank_features(prop.debug.features) @ w
        hit = box_iou(prop.debug.candidates, np.array([o.box2d for o in f.objects])).max(axis=1) >= 0.5
        pos += list(s[hit])
        neg += list(s[~hit])
    assert pos and neg and np.mean(pos) > np.mean(neg)
