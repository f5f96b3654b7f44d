"""Built-in proposals: the proposal classifier's re-decision and the class-given second pass."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from shape_detector import ShapeDetector
from shape_detector.classes import CLASS_TO_ID, CLASSES, NUM_CLASSES
from shape_detector.model.classifier import ClassifierConfig, ProposalClassifier, save_classifier
from shape_detector.model.predictor import refined_score
from toy_scenes import box_part, chair_parts, toy_scene, up_from_pitch_roll


@pytest.fixture(scope="module")
def scene():
    parts = [box_part(0.25, 2.6, 0.53, 1.0, 1.17, yaw=0.35)]
    chair = chair_parts(-0.9, 2.2, yaw=0.5)
    return toy_scene([("dresser", parts), ("chair", chair)], up=up_from_pitch_roll(12.0), cam_height=1.3, seed=3)


class FixedClassifier:
    """Stands in for a trained classifier: every candidate is 'bed' with probability 0.6."""

    config = ClassifierConfig()

    def __init__(self) -> None:
        self.calls = 0

    def probabilities(self, points, globals_):
        self.calls += 1
        assert points.shape[0] == globals_.shape[0] >= 1
        p = np.full((len(points), NUM_CLASSES + 1), 0.4 / NUM_CLASSES)
        p[:, CLASS_TO_ID["bed"]] = 0.6
        return p


def test_classifier_decides_class_and_score_of_builtin_proposals(scene):
    det = ShapeDetector(score_threshold=0.0, classifier=False, refine=False)
    det.classifier = FixedClassifier()
    objects = det.detect(scene.rgb, scene.depth, scene.K)
    assert objects and det.classifier.calls == 1
    kept = [o for o in objects if o.score > 0.1]  # Soft-NMS copies carry a tenth of the score
    assert kept and all(o.class_name == "bed" and o.score == pytest.approx(0.6) for o in kept)
    assert all(o.class_scores[CLASS_TO_ID["bed"]] == pytest.approx(0.6) for o in kept)


def test_classifier_decides_given_boxes_without_a_class_only(scene):
    det = ShapeDetector(score_threshold=0.0, classifier=False, refine=False)
    det.classifier = FixedClassifier()
    dresser, chair = scene.objects
    objects = det.detect(scene.rgb, scene.depth, scene.K, boxes2d=[(*dresser.box2d, None), (*chair.box2d, "chair")])
    assert det.classifier.calls == 1 and len(objects) == 2
    by_box = {tuple(np.round(o.box2d, 3)): o for o in objects}
    agnostic, given = by_box[tuple(np.round(dresser.box2d, 3))], by_box[tuple(np.round(chair.box2d, 3))]
    assert agnostic.class_name == "bed" and agnostic.score == pytest.approx(0.6)
    assert given.class_name == "chair"  # a given class is kept, never re-decided
    det.detect(scene.rgb, scene.depth, scene.K, boxes2d=[(*chair.box2d, "chair")])
    assert det.classifier.calls == 1  # no class-less box: the classifier is not run


def test_reclassify_changes_only_the_listed_frustums(scene):
    from shape_detector.detector import reclassify

    det = ShapeDetector(score_threshold=0.0, classifier=False, refine=False)
    prep = det.prepare(scene.rgb, scene.depth, scene.K)
    first = det.predictor.predict(prep.frustums, [None] * len(prep.frustums))
    out = reclassify(FixedClassifier(), prep, first, [1])
    assert out[0] is first[0] and out[1].class_name == "bed"
    assert reclassify(FixedClassifier(), prep, first, []) == first


def test_second_pass_runs_the_predicted_class_given(scene):
    det = ShapeDetector(score_threshold=0.0, classifier=False, refine=False)
    prep = det.prepare(scene.rgb, scene.depth, scene.K)
    pred = det.predictor
    first = pred.predict(prep.frustums, [None] * len(prep.frustums))
    second = pred.refine(prep.frustums, first, min_score=0.0)
    # (second=True: the second pass's arithmetic; under `auto` given boxes run in int8)
    given = pred.predict(prep.frustums, [CLASS_TO_ID[p.class_name] for p in first], second=True)
    for f, s, g in zip(first, second, given):
        assert s.class_name == f.class_name
        np.testing.assert_array_equal(s.class_probs, f.class_probs)  # the class is the first pass's
        np.testing.assert_allclose(s.center, g.center)  # the box is the class-given pass's
        np.testing.assert_allclose(s.size, g.size)
        assert s.score == pytest.approx(np.sqrt(f.score * g.objectness))
    # below min_score a prediction is returned unchanged
    top = max(p.score for p in first)
    kept = pred.refine(prep.frustums, first, min_score=top + 1e-6)
    assert all(k is f for k, f in zip(kept, first))


def test_refine_option_changes_builtin_boxes_only(scene):
    on = ShapeDetector(score_threshold=0.0, classifier=False, refine=True, refine_min_score=0.0)
    off = ShapeDetector(score_threshold=0.0, classifier=False, refine=False)
    a, b = on.detect(scene.rgb, scene.depth, scene.K), off.detect(scene.rgb, scene.depth, scene.K)
    assert len(a) >= 1 and len(b) >= 1
    centres_a = np.array(sorted(tuple(o.center.round(6)) for o in a))
    centres_b = np.array(sorted(tuple(o.center.round(6)) for o in b))
    assert centres_a.shape != centres_b.shape or not np.allclose(centres_a, centres_b)
    box = [(*scene.objects[0].box2d, "dresser")]  # a class given: no second pass, identical results
    ga, gb = on.detect(scene.rgb, scene.depth, scene.K, boxes2d=box), off.detect(scene.rgb, scene.depth, scene.K, boxes2d=box)
    np.testing.assert_allclose(ga[0].center, gb[0].center)


def test_refined_score_is_a_geometric_mean():
    assert refined_score(0.81, 0.25) == pytest.approx(0.45)
    assert refined_score(0.5, 0.0) == 0.0 and refined_score(-0.1, 0.5) == 0.0


def test_classifier_file_loads_and_missing_file_raises(tmp_path, scene):
    torch.manual_seed(0)
    path = tmp_path / "c.pt"
    save_classifier(ProposalClassifier(ClassifierConfig(widths=(8, 16), fc=(16,))).eval(), path)
    det = ShapeDetector(score_threshold=0.0, classifier=path)
    objects = det.detect(scene.rgb, scene.depth, scene.K)
    assert all(o.class_name in CLASSES and 0.0 <= o.score <= 1.0 for o in objects)
    with pytest.raises(FileNotFoundError, match="classifier"):
        ShapeDetector(classifier=tmp_path / "missing.pt")


def test_each_builtin_proposer_gets_the_classifier_trained_on_its_candidates(tmp_path, monkeypatch):
    from shape_detector import detector as det_mod

    assert det_mod.packaged_classifier("geometric") == det_mod.DEFAULT_CLASSIFIER
    assert det_mod.packaged_classifier("external") == det_mod.DEFAULT_CLASSIFIER
    hybrid = tmp_path / "classifier_hybrid.pt"
    monkeypatch.setattr(det_mod, "HYBRID_CLASSIFIER", hybrid)
    assert det_mod.packaged_classifier("hybrid") == det_mod.DEFAULT_CLASSIFIER  # not packaged: the general one
    torch.manual_seed(0)
    save_classifier(ProposalClassifier(ClassifierConfig(widths=(8, 16), fc=(16,))).eval(), hybrid)
    assert det_mod.packaged_classifier("hybrid") == hybrid
    assert det_mod.packaged_classifier("learned") == det_mod.DEFAULT_CLASSIFIER
    det = ShapeDetector(proposal_source="hybrid")
    assert det.classifier.config.widths == (8, 16)  # the hybrid file, loaded by default
    assert ShapeDetector(proposal_source="hybrid", classifier="none").classifier is None


def test_reclassify_keeps_empty_frustums_at_zero(scene):
    from shape_detector.detector import reclassify

    det = ShapeDetector(score_threshold=0.0, classifier=False, refine=False)
    prep = det.prepare(scene.rgb, scene.depth, scene.K)
    first = det.predictor.predict(prep.frustums, [None] * len(prep.frustums))
    first[0] = replace(first[0], num_points_valid=0)
    out = reclassify(FixedClassifier(), prep, first)
    assert out[0].score == 0.0 and out[1].score == pytest.approx(0.6)


def test_first_pass_share_balances_the_two_stages():
    from shape_detector.detector import first_pass_share

    # before 10 ms, network 30, after 40: a share s gives 10 + 30 s against 30 (1 - s) + 40
    assert first_pass_share({"proposals_ms": 10.0, "network_ms": 30.0, "refine_ms": 40.0}) == pytest.approx(1.0)
    assert first_pass_share({"proposals_ms": 10.0, "network_ms": 20.0, "refine_ms": 10.0}) == pytest.approx(0.5)
    s = first_pass_share({"proposals_ms": 12.0, "network_ms": 14.0, "classifier_ms": 3.0, "post_ms": 4.0})
    assert 12.0 + 14.0 * s == pytest.approx(14.0 * (1 - s) + 7.0)
    # a first stage already the slower one keeps none of it
    assert first_pass_share({"proposals_ms": 30.0, "network_ms": 10.0, "post_ms": 15.0}) == 0.0
    assert first_pass_share({}) == 0.0 and first_pass_share(None) == 0.0


def test_first_pass_in_the_first_stage_gives_the_same_objects(scene):
    det = ShapeDetector(score_threshold=0.0)
    ref = det.detect(scene.rgb, scene.depth, scene.K)
    for share in (1.0, 0.5, 0.0):
        prep = det.first_pass(det.prepare(scene.rgb, scene.depth, scene.K), share)
        n = len(prep.frustums)
        assert len(prep.first or []) == (n if share == 1.0 else int(round(share * n)))
        got = det.finish(prep)
        assert len(prep.first) == n
        assert len(got) == len(ref) >= 1
        for g, r in zip(got, ref):
            assert g.class_name == r.class_name and g.score == pytest.approx(r.score, abs=1e-6)
            np.testing.assert_allclose(g.center, r.center, atol=1e-6)
        assert {"network_ms", "classifier_ms", "refine_ms", "post_ms", "total_ms"} <= set(det.last_timing)


@pytest.mark.parametrize("workers", [1, 2])
def test_second_pass_with_cached_segmentation_features_is_the_same(scene, workers):
    """The class one-hot enters the network after the segmentation PointNet, so the second
    pass may reuse the first pass's features: same boxes, masks and primitives."""
    from shape_detector.model.predictor import FrustumPredictor

    det = ShapeDetector(score_threshold=0.0, classifier=False, refine=False, workers=workers)
    prep = det.prepare(scene.rgb, scene.depth, scene.K)
    # eager, so the hooks below see which modules run (the traced graphs run without Python)
    pred = FrustumPredictor(det.weights, workers=workers, trace=False)
    plain = pred.predict(prep.frustums, [None] * len(prep.frustums))
    kept = pred.predict(prep.frustums, [None] * len(prep.frustums), keep_features=True)
    assert plain[0].seg_features is None
    glob, local = kept[0].seg_features
    assert glob.ndim == 1 and local.shape[0] == prep.frustums[0].points.shape[0]
    calls = []
    seg_mlp = pred.model.seg_mlp
    handle = seg_mlp.register_forward_hook(lambda *a: calls.append(1))
    try:
        seg_mlp.forward_max = (lambda f: lambda *a, **k: (calls.append(1), f(*a, **k))[1])(seg_mlp.forward_max)
        cached = pred.refine(prep.frustums, kept, min_score=0.0)
        n_cached = len(calls)
        full = pred.refine(prep.frustums, plain, min_score=0.0)
    finally:
        handle.remove()
        del seg_mlp.forward_max
    assert n_cached == 0 and len(calls) >= 1  # the cached pass never ran the segmentation PointNet
    assert len(cached) == len(full) >= 2
    for c, f in zip(cached, full):
        np.testing.assert_allclose(c.center, f.center, atol=1e-5)
        np.testing.assert_allclose(c.size, f.size, atol=1e-5)
        np.testing.assert_allclose(c.seg_prob, f.seg_prob, atol=1e-5)
        assert c.score == pytest.approx(f.score, abs=1e-5)
        assert len(c.primitives) == len(f.primitives)
    # a cache from other frustums is refused by shape
    with pytest.raises(ValueError, match="seg_features"):
        pred.predict(prep.frustums, seg_features=[None])
