"""The proposal classifier: its inputs by hand, its file round trip, its training, its labels."""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from shape_detector.classes import CLASS_TO_ID, NUM_CLASSES
from shape_detector.geometry import rot_z
from shape_detector.model.classifier import (
    GLOBAL_FEATURES,
    POINT_CHANNELS,
    ClassifierConfig,
    ProposalClassifier,
    candidate_inputs,
    load_classifier,
    save_classifier,
)
from shape_detector.training.classifier_data import label_candidates, tried_objects
from shape_detector.training.train_classifier import (
    ClassifierTrainConfig,
    class_weights,
    fit_temperature,
    mirror,
    train_classifier,
)

G = {name: i for i, name in enumerate(GLOBAL_FEATURES)}


def _one_candidate(floor_height):
    pts = np.zeros((1, 4, 6), np.float32)
    pts[0, :, 0] = [1.0, 3.0, 10.0, 10.0]  # x: two foreground points at 1 and 3, two background far right
    pts[0, :, 1] = [2.0, 2.0, 5.0, 5.0]
    pts[0, :, 2] = [-0.5, -1.0, 0.2, 0.2]  # z up from the camera
    pts[0, :, 3:] = 0.5
    seg = np.array([[0.9, 0.8, 0.1, 0.2]], np.float32)
    probs = np.full((1, NUM_CLASSES + 1), 1.0 / (NUM_CLASSES + 1))
    return candidate_inputs(
        pts, seg, center_F=[[2.0, 2.0, -0.75]], size=[[1.0, 0.5, 0.5]], class_probs=probs, valid=[400],
        boxes2d=[[0.0, 100.0, 50.0, 240.0]], proposal_score=[0.7], image_size=(320, 240), floor_height=floor_height,
    )


def test_candidate_inputs_by_hand():
    p, g = _one_candidate(floor_height=1.2)
    assert p.shape == (1, 4, POINT_CHANNELS) and g.shape == (1, len(GLOBAL_FEATURES))
    # horizontal offsets from the foreground mean (2, 2); heights above the floor 1.2 m below the camera
    np.testing.assert_allclose(p[0, :, 0], [-1.0, 1.0, 8.0, 8.0])
    np.testing.assert_allclose(p[0, :, 1], [0.0, 0.0, 3.0, 3.0])
    np.testing.assert_allclose(p[0, :, 2], [0.7, 0.2, 1.4, 1.4], atol=1e-6)
    np.testing.assert_allclose(p[0, :, 6], [0.9, 0.8, 0.1, 0.2])
    f = g[0]
    assert f[G["bottom"]] == pytest.approx(1.2 - 0.75 - 0.25)
    assert f[G["top"]] == pytest.approx(1.2 - 0.75 + 0.25)
    assert f[G["floor_known"]] == 1.0
    assert f[G["range"]] == pytest.approx(np.hypot(2.0, 2.0))
    assert f[G["fg_share"]] == pytest.approx(0.5)
    assert f[G["box_w"]] == pytest.approx(50 / 320) and f[G["box_h"]] == pytest.approx(140 / 240)
    assert (f[G["cut_left"]], f[G["cut_right"]], f[G["cut_top"]], f[G["cut_bottom"]]) == (1.0, 0.0, 0.0, 1.0)
    assert f[G["proposal_score"]] == pytest.approx(0.7)
    assert f[G["logp_0"]] == pytest.approx(np.log(1 / 11), rel=1e-5)


def test_candidate_inputs_without_a_floor_use_the_prior_height():
    p, g = _one_candidate(floor_height=None)
    prior = ClassifierConfig().prior_height
    np.testing.assert_allclose(p[0, :2, 2], [prior - 0.5, prior - 1.0], atol=1e-6)
    assert g[0, G["floor_known"]] == 0.0


def test_mirror_swaps_the_left_and_right_cut_flags():
    p, g = _one_candidate(floor_height=1.2)
    pm, gm = mirror(torch.as_tensor(p), torch.as_tensor(g))
    np.testing.assert_allclose(pm[0, :, 0].numpy(), -p[0, :, 0])
    assert gm[0, G["cut_left"]] == 0.0 and gm[0, G["cut_right"]] == 1.0
    np.testing.assert_allclose(pm[0, :, 1:].numpy(), p[0, :, 1:])


def test_save_load_round_trip(tmp_path):
    torch.manual_seed(0)
    model = ProposalClassifier(ClassifierConfig(widths=(8, 16), fc=(16,), num_points=4)).eval()
    model.temperature.fill_(1.7)
    p, g = _one_candidate(floor_height=1.2)
    path = tmp_path / "c.pt"
    save_classifier(model, path, meta={"note": 1})
    loaded, meta = load_classifier(path)
    assert meta["note"] == 1 and float(loaded.temperature) == pytest.approx(1.7, rel=1e-3)
    a, b = model.probabilities(p, g), loaded.probabilities(p, g)
    np.testing.assert_allclose(a, b, atol=2e-3)  # float16 storage
    assert a.shape == (1, NUM_CLASSES + 1) and a.sum() == pytest.approx(1.0)
    torch.save({"format": "other", "state_dict": {}}, tmp_path / "x.pt")
    with pytest.raises(ValueError, match="proposal-classifier"):
        load_classifier(tmp_path / "x.pt")
    torch.save({"format": "other"}, tmp_path / "y.pt")
    with pytest.raises(ValueError, match="not a shape_detector weights file"):
        load_classifier(tmp_path / "y.pt")


def test_fit_temperature_recovers_a_known_scale():
    torch.manual_seed(0)
    true = torch.randn(4000, 5) * 2.0
    y = torch.distributions.Categorical(logits=true).sample()
    t = fit_temperature(true * 3.0, y, torch.ones(4000))  # logits 3x too confident
    assert t == pytest.approx(3.0, rel=0.1)


def test_class_weights_by_hand():
    labels = np.array([0, 0, 0, 0, 1, NUM_CLASSES])
    w = class_weights(labels, np.ones(6), power=0.5)
    assert w[0] == pytest.approx(1.0) and w[1] == pytest.approx(2.0) and w[NUM_CLASSES] == pytest.approx(2.0)
    assert w[2] == 0.0  # absent classes get no weight


def _separable_rows(n: int, rng: np.random.Generator):
    """Candidates whose class is in the height of their points: a learnable toy problem."""
    labels = rng.integers(0, 3, n)
    pts = rng.normal(0, 0.05, (n, 16, POINT_CHANNELS)).astype(np.float32)
    pts[..., 2] += labels[:, None] * 0.5
    glob = rng.normal(0, 1, (n, len(GLOBAL_FEATURES))).astype(np.float32)
    return {"points": pts.astype(np.float16), "globals": glob, "label": labels.astype(np.int16),
            "weight": np.ones(n, np.float32), "frame_index": np.arange(n) // 4}


def test_training_learns_a_separable_toy_problem(tmp_path):
    ds = _separable_rows(400, np.random.default_rng(0))
    out = tmp_path / "cls.pt"
    log = train_classifier(
        ds, out, ClassifierTrainConfig(epochs=6, batch_size=32, lr=3e-3, val_fraction=0.25),
        ClassifierConfig(widths=(16, 32), fc=(32,), num_points=8, dropout=0.0), log=lambda s: None,
    )
    hist = log["history"]
    assert hist[-1]["train_loss"] < 0.5 * hist[0]["train_loss"]
    assert log["best"]["acc"] > 0.9
    model, meta = load_classifier(out)
    assert meta["best"]["epoch"] == log["best"]["epoch"]


def _box(center, size, yaw=0.0):
    return SimpleNamespace(center=np.asarray(center, float), size=np.asarray(size, float), rotation=rot_z(yaw))


def _gt(center, size, cls, visible=1.0, box2d=(0, 0, 10, 10)):
    g = _box(center, size)
    g.class_name, g.visible_fraction, g.box2d = cls, visible, box2d
    return g


def test_labels_follow_the_evaluation():
    up = np.array([0.0, 0.0, 1.0])
    objects = [
        _gt([0, 0, 0], [1, 1, 1], "chair"),
        _gt([5, 0, 0], [1, 1, 1], "table"),
        _gt([9, 0, 0], [1, 1, 1], "bed", visible=0.05),  # "don't care"
    ]
    first = [
        _box([0.1, 0, 0], [1, 1, 1]),  # IoU 0.82 with the chair
        _box([5.8, 0, 0], [1, 1, 1]),  # IoU 0.11 with the table ...
        _box([9, 0, 0], [1, 1, 1]),  # on the ignored bed
        _box([20, 0, 0], [1, 1, 1]),  # nothing
    ]
    refined = {1: (1, _box([5.05, 0, 0], [1, 1, 1]))}  # ... but its class-given pass finds it
    label, weight, iou = label_candidates(first, refined, objects, up)
    assert list(label) == [CLASS_TO_ID["chair"], CLASS_TO_ID["table"], NUM_CLASSES, NUM_CLASSES]
    assert list(weight) == [1.0, 1.0, 0.0, 1.0]
    assert iou[0] == pytest.approx(0.9 / 1.1) and iou[1] == pytest.approx(0.95 / 1.05)
    # without the class-given pass the table candidate is background
    label, _, _ = label_candidates(first, {}, objects, up)
    assert label[1] == NUM_CLASSES


def test_tried_objects_by_2d_overlap():
    objects = [_gt([0, 0, 0], [1, 1, 1], "chair", box2d=(0, 0, 10, 10)),
               _gt([0, 0, 0], [1, 1, 1], "lamp", box2d=(20, 0, 30, 10))]  # not a class: never tried
    got = tried_objects([(0, 0, 10, 9), (20, 0, 30, 10), (50, 50, 60, 60)], objects)
    assert got == {0: 0}


@pytest.mark.parametrize("trace", [True, False])
def test_classifier_predictor_matches_the_classifier(trace):
    from shape_detector.model.classifier import GLOBAL_FEATURES, POINT_CHANNELS, ClassifierPredictor

    torch.manual_seed(0)
    model = ProposalClassifier(ClassifierConfig(widths=(8, 16), fc=(16,), num_points=32)).eval()
    with torch.no_grad():  # BatchNorm statistics that folding must carry over
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.uniform_(-0.3, 0.3)
                m.running_var.uniform_(0.5, 2.0)
    model.temperature.fill_(1.3)
    rng = np.random.default_rng(0)
    p = rng.normal(0, 1, (6, 50, POINT_CHANNELS)).astype(np.float32)  # 50 points: 32 evenly spaced used
    g = rng.normal(0, 1, (6, len(GLOBAL_FEATURES))).astype(np.float32)
    want = model.probabilities(p, g)
    import copy

    fp32 = ClassifierPredictor(copy.deepcopy(model), precision="fp32", trace=trace, backend="torch")
    np.testing.assert_allclose(fp32.probabilities(p, g), want, atol=1e-6)
    np.testing.assert_allclose(fp32.probabilities(p[:1], g[:1]), want[:1], atol=1e-6)
    bf16 = ClassifierPredictor(copy.deepcopy(model), precision="bf16", trace=trace)
    got = bf16.probabilities(p, g)
    np.testing.assert_allclose(got, want, atol=0.05)  # bfloat16 arithmetic
    np.testing.assert_allclose(got.sum(1), 1.0, atol=1e-6)  # still a distribution, computed in float32
    assert fp32.probabilities(p[:0], g[:0]).shape == (0, NUM_CLASSES + 1)
    fp32.warm_up(max_batch=3)
    assert fp32._run.traced == (1 if trace else 0)  # one graph serves every batch size


def test_train_classifier_refuses_candidates_built_with_other_settings(tmp_path, capsys):
    from shape_detector.training import classifier_cli

    parser = argparse.ArgumentParser()
    classifier_cli.configure_parser(parser)
    data, out = tmp_path / "data", tmp_path / "run"
    data.mkdir()
    out.mkdir()
    geometric = parser.parse_args(["--data", str(data), "--out", str(out)])
    (out / "candidates.json").write_text(json.dumps(classifier_cli._candidate_settings(geometric)))
    hybrid = parser.parse_args(["--data", str(data), "--out", str(out), "--proposal-source", "hybrid"])
    assert classifier_cli.main(hybrid) == 2
    assert "other settings" in capsys.readouterr().err
