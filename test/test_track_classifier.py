"""The scene map's track classifier: features, fitting, files, and what the map publishes with it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shape_detector.classes import CLASSES
from shape_detector.scene import SceneConfig, SceneMap
from shape_detector.scene import track_classifier as tc
from test_scene_support import detection, pose

T0 = pose(0.0, 0.0, 1.2, 0.0)
CHAIR = ((3.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)


def _onehot(name: str) -> np.ndarray:
    p = np.zeros(len(CLASSES))
    p[CLASSES.index(name)] = 1.0
    return p


def test_features_measure_size_height_and_neighbours():
    probs = np.stack([_onehot("bed"), _onehot("night_stand")])
    size = np.array([[1.6, 2.0, 0.6], [0.5, 0.4, 0.6]])
    # the night stand's bounding circle is 0.3 m from the bed's
    r_bed, r_ns = 0.5 * np.hypot(1.6, 2.0), 0.5 * np.hypot(0.5, 0.4)
    center = np.array([[0.0, 0.0, 0.3], [r_bed + r_ns + 0.3, 0.0, 0.35]])
    x = tc.track_features(probs, size, center, np.array([10, 4]), np.array([0.9, 0.6]), floor_z=0.0)
    f = {n: x[:, i] for i, n in enumerate(tc.FEATURES)}
    assert x.shape == (2, len(tc.FEATURES))
    np.testing.assert_allclose(f["log_length"], np.log([2.0, 0.5]))
    np.testing.assert_allclose(f["log_width"], np.log([1.6, 0.4]))
    np.testing.assert_allclose(f["log_height"], np.log([0.6, 0.6]))
    np.testing.assert_allclose(f["log_length*log_height"], np.log([2.0, 0.5]) * np.log(0.6))
    np.testing.assert_allclose(f["bottom_above_floor"], [0.0, 0.05], atol=1e-12)
    np.testing.assert_allclose(f["log_p_bed"], [0.0, np.log(tc.PROB_FLOOR)])
    np.testing.assert_allclose(f["near_bed"], [0.0, np.exp(-0.3 / tc.CONTEXT_SCALE)])  # a track is not its own neighbour
    np.testing.assert_allclose(f["near_chair"], [0.0, 0.0])
    assert tc.track_features(np.zeros((0, len(CLASSES))), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                             np.zeros(0)).shape == (0, len(tc.FEATURES))


def _toy(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Dressers (tall) and night stands (low) whose detections call every one a night stand,
    and low-scored background: only the size and the score tell them apart."""
    y = rng.integers(0, 3, n)
    h = np.where(y == 0, rng.uniform(1.0, 1.6, n), rng.uniform(0.45, 0.75, n))
    size = np.stack([rng.uniform(0.4, 1.2, n), rng.uniform(0.4, 0.6, n), h], 1)
    center = np.stack([np.arange(n) * 10.0, np.zeros(n), h / 2], 1)  # far apart: no neighbours
    probs = np.tile(_onehot("night_stand"), (n, 1)) * 0.8 + 0.02
    score = np.where(y == 2, rng.uniform(0.0, 0.3, n), rng.uniform(0.6, 1.0, n))
    x = tc.track_features(probs, size, center, np.full(n, 8), score)
    labels = np.choose(y, [CLASSES.index("dresser"), CLASSES.index("night_stand"), tc.OUTPUTS.index("background")])
    return x, labels


def test_fit_learns_what_the_evidence_misses_and_the_file_round_trips(tmp_path):
    x, y = _toy(300, np.random.default_rng(0))
    model = tc.fit(x, y, l2=1e-3, meta={"note": "toy"})
    xt, yt = _toy(200, np.random.default_rng(1))
    k, score, probs = model.decide(xt)
    fg = yt < len(CLASSES)
    assert np.mean(k[fg] == yt[fg]) > 0.95
    assert np.all(score[~fg] < 0.5) and np.median(score[fg]) > 0.8  # background scores low
    np.testing.assert_allclose(probs.sum(1), 1.0)
    path = tmp_path / "tc.json"
    model.save(path)
    back = tc.TrackClassifier.load(path)
    np.testing.assert_allclose(back.probabilities(xt), model.probabilities(xt), rtol=1e-12)
    assert back.meta == {"note": "toy"}
    d = json.loads(path.read_text())
    d["features"] = d["features"][:-1]
    with pytest.raises(ValueError, match="features"):
        tc.TrackClassifier.from_dict(d)
    with pytest.raises(ValueError):
        tc.fit(x[:, :5], y)


def test_loading_by_setting(tmp_path):
    assert tc.load_track_classifier("") is None and tc.load_track_classifier("none") is None
    with pytest.raises(FileNotFoundError):
        tc.load_track_classifier(str(tmp_path / "missing.json"))
    packaged = tc.load_track_classifier("default")
    assert packaged is not None and packaged.meta["examples"] > 500
    assert packaged.weights.shape == (len(tc.FEATURES), len(tc.OUTPUTS))


def _always(name: str, tmp_path) -> str:
    """A classifier file that calls every track ``name`` with probability about 0.4 (the
    rest background)."""
    f, k = len(tc.FEATURES), len(tc.OUTPUTS)
    bias = np.full(k, -20.0)
    bias[CLASSES.index(name)] = np.log(0.4)
    bias[-1] = np.log(0.6)
    model = tc.TrackClassifier(np.zeros(f), np.ones(f), np.zeros((f, k)), bias)
    path = tmp_path / f"{name}.json"
    model.save(path)
    return str(path)


def test_the_map_publishes_the_classifiers_decision_and_restores_it_as_saved(tmp_path):
    det = detection(*CHAIR, T0)
    plain = SceneMap(SceneConfig(track_classifier=""))
    decided = SceneMap(SceneConfig(track_classifier=_always("sofa", tmp_path)))
    for i in range(5):
        plain.update([det], T0, None, None, stamp_ns=i)
        decided.update([det], T0, None, None, stamp_ns=i)
    (a,), (b,) = plain.objects(), decided.objects()
    assert a.class_name == "chair" and a.score > 0.5
    assert b.class_name == "sofa" and b.score == pytest.approx(0.4, abs=1e-6)
    assert b.class_probs == {"sofa": pytest.approx(1.0)}
    np.testing.assert_allclose(b.center, a.center)  # only class and score change
    assert b.track_score == pytest.approx(a.score) and a.track_score == pytest.approx(a.score)
    assert decided.tracks[0].class_name == "chair"  # the track's own evidence is kept for association
    # saved and loaded: published as saved, though 0.4 is under publish_score
    again = SceneMap.from_json(decided.to_json(), SceneConfig(track_classifier=""))
    (c,) = again.objects()
    assert c.class_name == "sofa" and c.score == pytest.approx(0.4, abs=1e-6)
    assert c.track_score == pytest.approx(a.score, abs=1e-3)  # the track's own score survives the file
    # observed again, the loaded track is decided afresh
    reloaded = SceneMap.from_json(decided.to_json(), SceneConfig(track_classifier=_always("bed", tmp_path)))
    assert reloaded.objects()[0].class_name == "sofa"
    reloaded.update([det], T0, None, None, stamp_ns=10)
    assert reloaded.objects()[0].class_name == "bed"


def test_a_map_without_confirmed_tracks_asks_nothing(tmp_path):
    m = SceneMap(SceneConfig(track_classifier=_always("sofa", tmp_path)))
    m.update([detection(*CHAIR, T0)], T0, None, None, stamp_ns=0)
    assert m.objects() == [] and m.tracks[0].decision is None


def test_training_examples_label_each_published_track_with_its_objects_class():
    from shape_detector.evaluation.scene_eval import SequenceData
    from shape_detector.evaluation.track_classifier_cli import cross_validate, sequence_examples
    from shape_detector.synth.generate import SynthConfig
    from shape_detector.synth.walkthrough import walkthrough
    from shape_detector.types import Object3D

    wt = walkthrough(1002, 10, config=SynthConfig(width=160, height=120, noise=False, jpeg=False))
    n = len(wt.gt_world)
    dets, pixels, visible = [], np.zeros((10, n)), np.zeros((10, n))
    for i, f in enumerate(wt.frames):
        dets.append([Object3D("sofa" if g.class_name == "chair" else g.class_name, 0.99, g.center, g.size,
                              g.rotation) for g in f.objects if g.visible_fraction > 0.3])
        for g in f.objects:
            pixels[i, g.instance_id - 1] = (f.instance_mask == g.instance_id).sum() * 16
            visible[i, g.instance_id - 1] = g.visible_fraction
    data = SequenceData(1002, dets, list(wt.poses), [f.depth for f in wt.frames], [f.K for f in wt.frames],
                        wt.stamps_ns, wt.gt_world, pixels, visible)
    x, y = sequence_examples(data)
    assert x.shape == (len(y), len(tc.FEATURES)) and len(y) >= 2
    names = [tc.OUTPUTS[k] for k in y]
    assert "sofa" not in {g.class_name for g in wt.gt_world}
    assert "chair" in names and "sofa" not in names  # the labelled class, whatever the detector said
    chairs = np.array(names) == "chair"
    assert np.all(x[chairs, tc.FEATURES.index("log_p_sofa")] > np.log(0.5))  # what the detections said
    assert np.all(y < len(CLASSES))  # perfect boxes: no background
    res = cross_validate([x, x], [y, y], folds=2, l2=1e-2)
    assert res["accuracy"] > 0.9 and np.isfinite(res["log_loss"])


def test_tracks_state_is_each_tracks_class_probs_and_score():
    from shape_detector.scene.tracks import Track, tracks_state

    rng = np.random.default_rng(0)
    tracks = [Track(id=i, center=np.zeros(3), size=np.ones(3), yaw=0.0, class_evidence=rng.random(len(CLASSES)) * (i > 0),
                    weight_sum=1.0, existence=0.0, observations=i, first_seen_ns=0, last_seen_ns=0, score_sum=0.7 * i)
              for i in range(5)]  # the first without evidence or observations
    probs, score = tracks_state(tracks)
    np.testing.assert_allclose(probs, [t.class_probs for t in tracks])
    np.testing.assert_allclose(score, [t.score for t in tracks])
    assert tracks_state([])[0].shape == (0, len(CLASSES))


def test_planning_doubts_a_track_by_its_own_score_not_the_class_probability():
    from shape_detector.ar.margins import DOUBT_SCORE, without_doubtful
    from shape_detector.scene.grid import NavGrid
    from shape_detector.scene.types import SceneObject

    grid = NavGrid(0.05, np.array([0.0, 0.0]), np.full((40, 40), 100, dtype=np.int8), 0.0)
    box = dict(center=np.array([1.0, 1.0, 0.4]), size=np.array([0.6, 0.6, 0.8]), rotation=np.eye(3))
    torn = SceneObject(1, "table", 0.45, class_probs={"table": 0.5, "desk": 0.45}, track_score=0.9, **box)
    assert torn.score < DOUBT_SCORE
    assert without_doubtful(grid, [torn]) is grid  # sure it is there, unsure which class
    ghost = SceneObject(1, "table", 0.9, track_score=0.3, **box)
    assert (without_doubtful(grid, [ghost]).data == -1).any()
    legacy = SceneObject(1, "table", 0.3, **box)  # saved before track scores: its score stands in
    assert (without_doubtful(grid, [legacy]).data == -1).any()


def test_fitting_cli_refuses_bad_options_and_a_missing_network(tmp_path, capsys):
    import argparse

    from shape_detector.evaluation import track_classifier_cli as cli

    parser = argparse.ArgumentParser()
    cli.configure_parser(parser)
    assert cli.main(parser.parse_args(["--sequences", "1", "--folds", "2", "-o", str(tmp_path / "t.json")])) == 2
    assert "--sequences" in capsys.readouterr().err
    args = parser.parse_args(["--weights", str(tmp_path / "none.pt"), "-o", str(tmp_path / "t.json")])
    assert cli.main(args) == 2
    assert "none.pt" in capsys.readouterr().err and not (tmp_path / "t.json").exists()
