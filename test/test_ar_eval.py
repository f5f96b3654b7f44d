"""evaluate-ar: the metrics are perfect on the true scene and drop on a shifted one."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from shape_detector.ar import ArScene
from shape_detector.scene.types import SceneObject, ScenePrimitive
from shape_detector.evaluation import ar_cli
from shape_detector.evaluation.ar_eval import STRUCTURE_ID0, evaluate_map, gt_map, seen_objects, truth_from_layout
from shape_detector.synth.generate import SynthConfig
from shape_detector.synth.walkthrough import walkthrough


@pytest.fixture(scope="module")
def walk():
    wt = walkthrough(5, 6, config=SynthConfig(width=160, height=120))
    truth = truth_from_layout(wt.scene)
    cams = [(T, f.K, 160, 120) for T, f in zip(wt.poses, wt.frames)]
    return wt, truth, cams


def test_truth_of_the_room(walk) -> None:
    wt, truth, _ = walk
    assert [o.id for o in truth.objects.objects] == list(range(1, len(wt.scene.objects) + 1))
    assert any(o.id >= STRUCTURE_ID0 for o in truth.full.objects)
    g = truth.grid
    assert set(np.unique(g.data)) <= {0, 100}
    # cells under an object's blocking part are occupied, the room's outside too
    o = truth.objects.objects[0]
    tall = [p for p in o.primitives if p.center[2] - 0.5 * p.size[2] < 1.8]
    rc = np.floor((tall[0].center[:2] - g.origin) / g.resolution).astype(int)[::-1]
    assert g.data[rc[0], rc[1]] == 100 and g.data[0, 0] == 100
    assert (g.data == 0).mean() > 0.2


def test_true_scene_scores_perfectly(walk) -> None:
    wt, truth, cams = walk
    r = evaluate_map(truth, gt_map(truth), cams, seen_objects(wt.frames, 50, 1), np.random.default_rng(0),
                     n_rays=500, n_points=500, n_pairs=10)
    assert r["ray_within_5cm"] == 1.0 and r["rays_used"] > 50
    assert r["ray_floor_within_5cm"] == 1.0 and r["rays_floor"] > 20  # the true grid's floor at z = 0
    assert r["collide_precision"] == 1.0 and r["collide_recall"] == 1.0 and r["collide_points"] > 100
    assert r["plan_found"] == 1.0 and r["plan_clear"] == 1.0 and r["plan_pairs"] >= 5


def test_shifted_scene_scores_worse(walk) -> None:
    wt, truth, cams = walk
    shift = np.array([0.3, 0.0, 0.0])
    moved = [SceneObject(o.id, o.class_name, 1.0, o.center + shift, o.size, o.rotation, primitives=[ScenePrimitive(p.center + shift, p.size, p.rotation) for p in o.primitives])
             for o in truth.objects.objects]
    r = evaluate_map(truth, ArScene(moved, truth.grid), cams, seen_objects(wt.frames, 50, 1),
                     np.random.default_rng(0), n_rays=500, n_points=500, n_pairs=5)
    assert r["ray_within_5cm"] < 0.8
    assert r["collide_precision"] < 0.9 and r["collide_recall"] < 0.9


def test_cli_gt_map(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    p = argparse.ArgumentParser()
    ar_cli.configure_parser(p)
    out = tmp_path / "ar.json"
    args = p.parse_args(["--gt-map", "--seeds", "5", "--frames", "4", "--width", "160", "--height", "120",
                         "--rays", "300", "--points", "300", "--pairs", "5", "--json", str(out)])
    assert ar_cli.main(args) == 0
    text = capsys.readouterr().out
    assert "ray_within_5cm: 1.000" in text and "FAIL" not in text
    assert json.loads(out.read_text())["mean"]["collide_recall"] == 1.0


def test_cli_takes_the_detector_flags(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    p = argparse.ArgumentParser()
    ar_cli.configure_parser(p)
    args = p.parse_args(["--seeds", "5", "--frames", "2", "--weights", str(tmp_path / "missing.pt")])
    assert ar_cli.main(args) == 2
    assert "missing.pt" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        p.parse_args(["--max-objects", "0"])  # refused with the reason, as the node's parameters are
    args = p.parse_args(["--seeds", "5", "--frames", "2", "--track-classifier", str(tmp_path / "none.json")])
    assert ar_cli.main(args) == 2
    assert "none.json" in capsys.readouterr().err


@pytest.mark.slow
def test_detector_map_pipeline(tmp_path: Path) -> None:
    from shape_detector.evaluation.ar_eval import evaluate_walkthrough

    r = evaluate_walkthrough(5, 6, 320, 240, n_rays=300, n_points=300, n_pairs=5, save_map=str(tmp_path / "m.json"),
                             track_classifier="")
    assert (tmp_path / "m.json").is_file()
    for k in ("ray_within_5cm", "collide_precision", "collide_recall"):
        assert 0.0 <= r[k] <= 1.0
    assert r["objects_true"] >= 4
