"""Scene evaluation metrics on a small walk-through with a perfect (GT) detector."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.evaluation.scene_eval import (SequenceData, grid_iou, run_map, score_sequences, seen_frames,
                                                  with_runner_up)
from shape_detector.synth.generate import SynthConfig
from shape_detector.synth.walkthrough import walkthrough
from shape_detector.types import Object3D


@pytest.fixture(scope="module")
def perfect() -> SequenceData:
    wt = walkthrough(1002, 12, config=SynthConfig(width=160, height=120, noise=False, jpeg=False))
    n = len(wt.gt_world)
    dets, pixels, visible = [], np.zeros((12, n)), np.zeros((12, n))
    for i, f in enumerate(wt.frames):
        dets.append([Object3D(g.class_name, 0.99, g.center, g.size, g.rotation, primitives=list(g.parts))
                     for g in f.objects if g.visible_fraction > 0.3])
        for g in f.objects:
            pixels[i, g.instance_id - 1] = (f.instance_mask == g.instance_id).sum() * 16  # as at 640 x 480
            visible[i, g.instance_id - 1] = g.visible_fraction
    return SequenceData(1002, dets, list(wt.poses), [f.depth for f in wt.frames], [f.K for f in wt.frames],
                        wt.stamps_ns, wt.gt_world, pixels, visible)


def test_perfect_detections_give_a_perfect_map(perfect):
    res = score_sequences([perfect])
    assert res["objects"] >= 2
    assert res["map_mAP"]["0.25"] == pytest.approx(100.0)
    assert res["map_mAP"]["0.5"] == pytest.approx(100.0)
    assert res["duplicates_per_object"] == 0.0 and res["id_switches_per_object"] == 0.0
    assert res["jitter_cm"] < 0.5
    assert res["grid_iou"] > 0.9
    assert res["stack_mAP"]["0.25"] <= res["map_mAP"]["0.25"] + 1e-9
    assert res["object_iou"]["median"] > 0.9 and res["object_iou"]["0.5"] == 1.0


def test_per_object_iou_counts_only_same_class_tracks(perfect):
    from shape_detector.evaluation.scene_eval import _same_class_iou

    g = [x for x in perfect.gt_world][:2]
    right = Object3D(g[0].class_name, 0.9, g[0].center, g[0].size, g[0].rotation)
    wrong = Object3D("bathtub" if g[1].class_name != "bathtub" else "bed", 0.9, g[1].center, g[1].size, g[1].rotation)
    assert _same_class_iou([right, wrong], g) == pytest.approx([1.0, 0.0])
    assert _same_class_iou([], g) == [0.0, 0.0] and _same_class_iou([right], []) == []


def test_runner_up_copies_score_the_second_class_by_its_share():
    from shape_detector.scene.types import SceneObject

    o = SceneObject(1, "desk", 0.8, np.zeros(3), np.ones(3), np.eye(3), class_probs={"desk": 0.6, "table": 0.3,
                                                                                    "chair": 0.1})
    plain = SceneObject(2, "bed", 0.9, np.ones(3), np.ones(3), np.eye(3))
    out = with_runner_up([o, plain])
    assert [(x.class_name, round(x.score, 6)) for x in out] == [("desk", 0.8), ("table", 0.4), ("bed", 0.9)]
    assert out[1].id == 1 and o.class_name == "desk"  # a copy; the input is unchanged


def test_grid_iou_of_the_truth_is_one_and_of_nothing_zero(perfect):
    m, _ = run_map(perfect)
    seen = seen_frames(perfect)
    gts = [g for g, n in zip(perfect.gt_world, seen) if n >= 3]
    ignored = [g for g, n in zip(perfect.gt_world, seen) if n < 3]
    full = grid_iou(m.grid(), gts, ignored=ignored)
    empty = m.grid()
    empty.data[empty.data == 100] = 0
    assert grid_iou(empty, gts, ignored=ignored) == 0.0
    assert full > 0.9


def test_cli_runs_and_prints_json(monkeypatch, capsys):
    import argparse
    import json

    import shape_detector.detector as det_mod
    from shape_detector.evaluation import scene_cli

    seen = []

    class Fake:
        def __init__(self, config=None, **kw):
            seen.append(config)

        def detect(self, rgb, depth, K, up=None):
            return []

    monkeypatch.setattr(det_mod, "ShapeDetector", Fake)
    p = argparse.ArgumentParser()
    scene_cli.configure_parser(p)
    args = p.parse_args(["--sequences", "1", "--frames", "3", "--width", "96", "--height", "72", "--json", "--quiet",
                         "--weights", "candidate.pt", "--max-objects", "5"])
    assert scene_cli.main(args) == 0
    assert seen[0].weights == "candidate.pt" and seen[0].max_objects == 5 and seen[0].precision == "auto"
    res = json.loads(capsys.readouterr().out)
    assert res["sequences"] == 1 and res["tracks"] == 0
    assert set(res["map_mAP"]) == {"0.25", "0.5"}
    args = p.parse_args(["--sequences", "0"])
    assert scene_cli.main(args) == 2
    args = p.parse_args(["--sequences", "1", "--pose-noise", "0.01,0.5"])
    assert scene_cli.main(args) == 2 and "pose noise" in capsys.readouterr().err


def test_collect_feeds_the_map_the_noisy_poses_and_the_detector_their_gravity():
    from shape_detector.evaluation.pose_noise import PoseNoise
    from shape_detector.evaluation.scene_eval import collect

    class Recording:
        def __init__(self):
            self.ups = []

        def detect(self, rgb, depth, K, up=None):
            self.ups.append(up)
            return []

    det = Recording()
    noise = PoseNoise(drift=0.05, jitter_deg=2.0)
    data = collect([3], 4, 96, 72, detector=det, pose_noise=noise)[0]
    clean = collect([3], 4, 96, 72, detector=Recording())[0]
    assert any(not np.allclose(a, b) for a, b in zip(data.poses, clean.poses))
    for up, T in zip(det.ups, data.poses):
        np.testing.assert_allclose(up, T[:3, :3].T @ [0.0, 0.0, 1.0])
    est = Recording()
    collect([3], 2, 96, 72, detector=est, up="estimate")
    assert est.ups == [None, None]


@pytest.mark.parametrize("gt_2d", ["boxes", "classes"])
def test_collect_with_gt_2d_gives_the_detector_the_true_2d_boxes(gt_2d):
    from shape_detector.evaluation.runner import gt_boxes2d
    from shape_detector.evaluation.scene_eval import collect
    from shape_detector.synth.generate import SynthConfig
    from shape_detector.synth.walkthrough import walkthrough

    class Recording:
        def __init__(self):
            self.boxes = []

        def detect(self, rgb, depth, K, boxes2d=None, up=None):
            self.boxes.append(boxes2d)
            return []

    det = Recording()
    collect([3], 4, 96, 72, detector=det, gt_2d=gt_2d)
    frames = walkthrough(3, 4, config=SynthConfig(width=96, height=72)).frames
    want = [gt_boxes2d(f)[0] for f in frames]
    assert any(want) and len(det.boxes) == sum(1 for w in want if w)  # frames with nothing to give are skipped
    got = iter(det.boxes)
    for w in (w for w in want if w):
        assert next(got) == (w if gt_2d == "classes" else [b[:4] for b in w])


def test_given_boxes2d_refuses_an_unknown_choice():
    from shape_detector.evaluation.runner import given_boxes2d

    with pytest.raises(ValueError, match="gt_2d"):
        given_boxes2d(None, "masks")
    assert given_boxes2d(None, None) is None
