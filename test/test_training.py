"""Frustum dataset building, batch augmentation, training / checkpoint / resume, CLI."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch

from shape_detector.box_iou import box2d_iou
from shape_detector.geometry import points_in_box, rot_z
from shape_detector.model.config import ModelConfig
from shape_detector.model.io import load_checkpoint, load_weights
from shape_detector.model.primitives import coverage_loss
from shape_detector.training import frustum_dataset as fds
from shape_detector.training.calibration import calibration_stats, fit_temperature
from shape_detector.training.config import TrainConfig
from shape_detector.training.tensor_data import TensorData
from shape_detector.training.train import train

from test_model_scene import make_frame
from tolerances import assert_outputs_close, changed_keys, outputs_differ

# a small network without the later branches (the ModelConfig defaults are the shipped network,
# which has them): the tests grow each branch onto it
SMALL = dict(num_points=128, num_object_points=64, seg_widths=[16, 16, 32], seg_head_widths=[16], tnet_widths=[16, 32],
             tnet_fc=[16], box_widths=[16, 32], box_fc=[32], shape_fc=[32], shape_widths=[16, 32], cls_fc=[16],
             box_context_widths=[], box2_widths=[], shape_context_widths=[], shape_anchors=False)


@pytest.fixture(scope="module")
def ds():
    frames = [make_frame(s, 3) for s in range(6)]
    return fds.build_frustum_dataset(frames, num_points=128, augment_copies=2, rng_seed=0, negatives_per_frame=2)


def test_dataset_ground_truth_is_consistent(ds, tmp_path):
    s = fds.summary(ds)
    assert s["positives"] > 10 and s["negatives"] > 0 and s["frames"] == 6
    pos = np.nonzero(~ds["is_negative"])[0]
    for i in pos:
        p = ds["points"][i, :, :3].astype(np.float64)
        fg = ds["seg"][i] == 1
        assert fg.sum() > 0
        R = rot_z(float(ds["heading"][i]))
        inside = points_in_box(p[fg], ds["center"][i], ds["size"][i], R, margin=0.03)
        assert inside.mean() > 0.97
        # canonical parts lie inside the box, the surface samples on them
        k = int(ds["parts_count"][i])
        half = ds["size"][i] / 2 + 1e-3
        assert np.all(np.abs(ds["parts_center"][i, :k]) <= half)
        assert np.all(np.abs(ds["surface"][i].astype(np.float64)) <= half + 2e-3)
        # frame meta: F -> camera reproduces the camera-frame points of the frame
        assert ds["R_cu"][i].shape == (3, 3)
    neg = ds["is_negative"]
    assert np.all(ds["seg"][neg] == 0) and np.all(fds.cls_labels(ds)[neg] == 10)
    p = fds.save(ds, tmp_path / "f.npz")
    back = fds.load(p)
    assert set(back) == set(ds)
    assert np.array_equal(back["points"], ds["points"]) and fds.dataset_config(back)["num_points"] == 128
    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    assert not set(tr["frame_index"]) & set(va["frame_index"])
    assert fds.num_frustums(tr) + fds.num_frustums(va) == fds.num_frustums(ds)


def test_augmented_batches_stay_consistent(ds):
    data = TensorData(ds, torch.device("cpu"), 10)
    cfg = TrainConfig(mirror_prob=1.0, point_jitter=0.0, scale_min=0.9, scale_max=1.1)
    pos = torch.as_tensor(np.nonzero(~ds["is_negative"])[0])
    b = data.batch(pos, cfg, augment=True, generator=torch.Generator().manual_seed(0))
    b0 = data.batch(pos, cfg, augment=False, one_hot_mode="given")
    assert torch.allclose(b["heading"], np.pi - b0["heading"])
    for j in range(len(pos)):
        p = b["points"][j, :, :3].double().numpy()
        fg = b["seg"][j].numpy() == 1
        R = rot_z(float(b["heading"][j]))
        assert points_in_box(p[fg], b["center"][j].double().numpy(), b["size"][j].double().numpy(), R, margin=0.04).mean() > 0.97
    # GT parts still cover the GT surface samples after mirroring + scaling
    prims = {"center": b["parts_center"], "size": b["parts_size"], "rotation": b["parts_rotation"]}
    m = b["parts_mask"]
    prims = {k: torch.where(m.view(*m.shape, *([1] * (v.dim() - 2))), v, torch.zeros_like(v)) for k, v in prims.items()}
    cov = coverage_loss(b["surface"], prims, 1)
    assert float(cov.max()) < 1e-4
    # one-hot dropout: some rows all zero, the others one class
    bt = data.batch(torch.arange(data.n), TrainConfig(onehot_drop_prob=0.5), augment=False, one_hot_mode="train",
                    generator=torch.Generator().manual_seed(1))
    rs = bt["one_hot"].sum(1)
    assert set(rs.tolist()) <= {0.0, 1.0} and 0 < float(rs.mean()) < 1


def test_temperature_calibration():
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 3, 2000)
    logits = rng.normal(0, 1, (2000, 3))
    logits[np.arange(2000), labels] += 1.0
    T = fit_temperature(logits * 4, labels)  # over-confident by 4x
    assert 3.0 < T < 5.5
    before = calibration_stats(np.exp(logits * 4) / np.exp(logits * 4).sum(1, keepdims=True), labels)
    z = logits * 4 / T
    after = calibration_stats(np.exp(z) / np.exp(z).sum(1, keepdims=True), labels)
    assert after["ece"] < before["ece"] and after["nll"] < before["nll"]


def _cfg(**kw):
    d = dict(model=SMALL, epochs=2, batch_size=8, log_every=1000, num_threads=1, val_max_frustums=64, shape_iou_max=32,
             shape_iou_samples=256)
    d.update(kw)
    return TrainConfig.from_dict(d)


def test_train_checkpoint_resume_round_trip(ds, tmp_path):
    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    logs = []
    a = tmp_path / "a"
    train(_cfg(), tr, va, a, seed=3, print_fn=logs.append)
    for f in ("checkpoint.pt", "weights.pt", "best.pt", "log.csv", "log.json", "loss_curve.png", "val_metrics.json"):
        assert (a / f).is_file(), f
    assert any("ep 2/2" in s for s in logs)
    vm = json.loads((a / "val_metrics.json").read_text())
    assert "temperature" in vm["best.pt"]["calibration"] and "box_iou" in vm["best.pt"]["metrics"]
    ck = load_checkpoint(a / "checkpoint.pt")
    assert ck["epoch"] == 2 and len(ck["history"]["epochs"]) == 2
    # 1 epoch, then resume for the 2nd: same weights as the straight run
    b = tmp_path / "b"
    train(_cfg(epochs=2), tr, va, b, seed=3, print_fn=logs.append, stop_after_epochs=1)
    assert load_checkpoint(b / "checkpoint.pt")["epoch"] == 1
    train(_cfg(epochs=2), tr, va, b, seed=3, resume=True, print_fn=logs.append)
    ckb = load_checkpoint(b / "checkpoint.pt")
    assert ckb["epoch"] == 2 and len(ckb["history"]["epochs"]) == 2
    for k, v in ck["state_dict"].items():
        assert torch.allclose(v.float(), ckb["state_dict"][k].float(), atol=1e-5), k
    net, meta = load_weights(b / "weights.pt")
    assert meta["epoch"] == 2 and meta["tasks"] == ["box", "cls", "shape"]
    assert (b / "weights.pt").stat().st_size < 3_000_000


def test_cli_trains_from_npz_with_task_flags(ds, tmp_path):
    from shape_detector.training import cli

    p = fds.save(ds, tmp_path / "train.npz")
    parser = argparse.ArgumentParser()
    cli.configure_parser(parser)
    args = parser.parse_args([
        "--data", str(p), "--out", str(tmp_path / "run"), "--seed", "1", "--epochs", "1", "--tasks", "shape",
        "--device", "cpu", "--threads", "1",
        "--set", "model=" + json.dumps(SMALL), "--set", "batch_size=8", "--set", "val_max_frustums=32",
        "--set", "shape_iou_max=16", "--set", "shape_iou_samples=256",
    ])
    assert cli.main(args) == 0
    vm = json.loads((tmp_path / "run" / "val_metrics.json").read_text())
    m = vm["best.pt"]["metrics"]
    assert "shape_iou" in m and "box_iou" not in m and vm["tasks"] == ["shape"]
    _, meta = load_weights(tmp_path / "run" / "weights.pt")
    assert meta["tasks"] == ["shape"]


def test_proposal_frustums_are_labelled_by_2d_overlap():
    """Proposal frustums: positives overlap their object's box by >= 0.5 (2D IoU) and carry its
    GT; hard negatives overlap no labelled box by 0.25 or more; GT-box frustums can be left out."""
    from shape_detector.synth.generate import SynthConfig, generate_frame

    frames = [generate_frame(s, SynthConfig(width=320, height=240)) for s in (3, 4, 5)]
    ds = fds.build_frustum_dataset(frames, num_points=128, augment_copies=1, negatives_per_frame=0,
                                   gt_frustums=False, proposal_positives=3, proposal_negatives=3)
    s = fds.summary(ds)
    assert s["positives"] >= 3 and s["negatives"] >= 1 and set(s["neg_kinds"]) == {fds.NEG_PROPOSAL}
    assert s["positives"] <= 9 and s["negatives"] <= 9
    for i in range(fds.num_frustums(ds)):
        fr = frames[int(ds["frame_index"][i])]
        box = ds["box2d"][i]
        ious = [box2d_iou(box, o.box2d) for o in fr.objects]
        if ds["is_negative"][i]:
            assert max(ious, default=0.0) < 0.25 and ds["seg"][i].sum() == 0
        else:
            obj = fr.objects[int(ds["object_index"][i])]
            assert box2d_iou(box, obj.box2d) >= 0.5 and ds["seg"][i].sum() > 0
            assert np.allclose(ds["size"][i], obj.size, atol=1e-5)
    # the GT-box frustums of the same frames come on top when gt_frustums is on
    both = fds.build_frustum_dataset(frames, num_points=128, augment_copies=1, negatives_per_frame=0,
                                     proposal_positives=3, proposal_negatives=3)
    gt_only = fds.build_frustum_dataset(frames, num_points=128, augment_copies=1, negatives_per_frame=0)
    assert fds.num_frustums(both) == fds.num_frustums(ds) + fds.num_frustums(gt_only)


def test_init_weights_fine_tunes_from_a_trained_model(ds, tmp_path):
    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    train(_cfg(epochs=1), tr, va, tmp_path / "a", seed=3, print_fn=lambda s: None)
    logs = []
    # zero epochs of fine-tuning would be a no-op; one epoch at lr 0 must keep the weights
    train(_cfg(epochs=1, lr=0.0), tr, va, tmp_path / "b", seed=4, print_fn=logs.append,
          init_weights=tmp_path / "a" / "weights.pt")
    assert any("initialised from" in s for s in logs)
    a, _ = load_weights(tmp_path / "a" / "weights.pt")
    b, _ = load_weights(tmp_path / "b" / "weights.pt")
    for (k, v), w in zip(a.state_dict().items(), b.state_dict().values()):
        if "running" in k or "num_batches" in k or "temperature" in k:
            continue  # BN statistics keep updating in train mode; the temperature is re-fitted
        assert torch.allclose(v.float(), w.float()), k
    with pytest.raises(ValueError, match="model config"):
        train(_cfg(epochs=1, model=dict(SMALL, cls_fc=[8])), tr, va, tmp_path / "c", seed=4,
              print_fn=lambda s: None, init_weights=tmp_path / "a" / "weights.pt")


def test_class_path_frozen_names_the_modules_the_class_logits_never_read():
    from shape_detector.training.init_from import class_path_frozen as _class_path_frozen

    assert _class_path_frozen(["shape_ctx_mlp", "shape_mlp", "shape_head", "shape_anchor"])
    assert _class_path_frozen(["box2_mlp", "box2_head"]) and _class_path_frozen(["ctx_mlp", "box_head"])
    # the class head reads the segmentation and box PointNets, and the mask decides the box net's points
    for trainable in (None, [], ["cls_head"], ["shape_head", "seg_mlp"], ["box_mlp"], ["seg_out"], ["tnet_head"]):
        assert not _class_path_frozen(trainable), trainable


def test_trainable_prefixes_freeze_the_rest(ds, tmp_path):
    """trainable=[...]: only those modules change; frozen BatchNorm statistics stay put."""
    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    train(_cfg(epochs=1), tr, va, tmp_path / "a", seed=3, print_fn=lambda s: None)
    logs = []
    train(_cfg(epochs=1, tasks="shape", trainable=["shape_mlp", "shape_head"], lr=0.01), tr, va, tmp_path / "b",
          seed=4, print_fn=logs.append, init_weights=tmp_path / "a" / "weights.pt")
    assert any("frozen" in s for s in logs)
    a, _ = load_weights(tmp_path / "a" / "weights.pt")
    b, _ = load_weights(tmp_path / "b" / "weights.pt")
    sa, sb = a.state_dict(), b.state_dict()
    changed = changed_keys(sa, sb, ignore=["cls_temperature"])
    assert changed and all(k.startswith(("shape_mlp", "shape_head")) for k in changed), changed
    with pytest.raises(ValueError, match="no network part"):
        train(_cfg(epochs=1, trainable=["nothing_here"]), tr, va, tmp_path / "c", seed=4, print_fn=lambda s: None)


def test_reinit_starts_modules_fresh_and_may_change_the_primitive_mapping(ds, tmp_path):
    """reinit=[...]: those modules start from a fresh initialisation (all others from --init);
    re-initialising the shape head allows another primitive mapping (its minimum size), nothing
    else may differ."""
    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    train(_cfg(epochs=1), tr, va, tmp_path / "a", seed=3, print_fn=lambda s: None)
    init = tmp_path / "a" / "weights.pt"
    other_mapping = dict(SMALL, primitive_min_size_frac=0.02)
    logs = []
    train(_cfg(epochs=1, tasks="shape", model=other_mapping, reinit=["shape_head"],
               trainable=["shape_mlp", "shape_head"], lr=1e-9), tr, va, tmp_path / "b", seed=4,
          print_fn=logs.append, init_weights=init)
    assert any("fresh" in s for s in logs)
    a, _ = load_weights(init)
    b, _ = load_weights(tmp_path / "b" / "weights.pt")
    assert b.config.primitive_min_size_frac == pytest.approx(0.02)
    sa, sb = a.state_dict(), b.state_dict()
    fresh = {k for k in sa if k.startswith("shape_head") and not torch.allclose(sa[k].float(), sb[k].float())}
    assert "shape_head.out.weight" in fresh  # a fresh initialisation, not the init's trained layer
    assert all(k.startswith(("shape_head", "shape_mlp", "cls_temperature")) for k in changed_keys(sa, sb))
    with pytest.raises(ValueError, match="model config"):  # the mapping may only change with a fresh head
        train(_cfg(epochs=1, model=other_mapping), tr, va, tmp_path / "c", seed=4,
              print_fn=lambda s: None, init_weights=init)
    with pytest.raises(ValueError, match="no network part"):
        train(_cfg(epochs=1, reinit=["nothing_here"]), tr, va, tmp_path / "d", seed=4, print_fn=lambda s: None,
              init_weights=init)


def test_shape_anchors_start_at_the_class_templates_and_carry_over(ds, tmp_path):
    """A model with shape anchors, initialised from one without: the anchors are the class
    templates of the training data's GT parts and the head's output layer restarts at zero;
    a later fine-tune from it keeps its anchors."""
    from shape_detector.model.primitives import primitive_params
    from shape_detector.model.shape_anchors import class_templates

    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    train(_cfg(epochs=1), tr, va, tmp_path / "a", seed=3, print_fn=lambda s: None)
    anchored = dict(SMALL, shape_anchors=True)
    logs = []
    train(_cfg(epochs=1, tasks="shape", model=anchored, trainable=["shape_mlp", "shape_head", "shape_anchor"], lr=1e-9),
          tr, va, tmp_path / "b", seed=4, print_fn=logs.append, init_weights=tmp_path / "a" / "weights.pt")
    assert any("shape anchors" in s for s in logs)
    b, _ = load_weights(tmp_path / "b" / "weights.pt")
    assert b.config.shape_anchors
    use = np.where(tr["has_shape"] & ~tr["is_negative"], tr["parts_count"], 0)
    lo, hi, found = class_templates(tr["parts_center"], tr["parts_size"], tr["parts_rotation"], use, tr["size"],
                                    tr["class_id"], b.config.num_classes, b.config.num_primitives, seed=4)
    assert found.any()
    c = int(np.flatnonzero(found)[0])
    size = torch.tensor([[1.0, 2.0, 3.0]])
    p = primitive_params(b.shape_anchor.detach()[c].view(1, -1, 10), size, **b.config.primitive_kwargs())
    # weights files store float16: raw translations within ~5e-4, i.e. 1e-3 m in a 3 m box
    np.testing.assert_allclose(p["center"][0].numpy(), 0.5 * (lo[c] + hi[c]) * size.numpy(), atol=2e-3)
    assert float(b.shape_head.out.weight.detach().abs().max()) < 1e-6
    assert torch.all(b.shape_anchor.detach()[~torch.as_tensor(found)] == 0)
    logs = []
    train(_cfg(epochs=1, tasks="shape", model=anchored, trainable=["shape_head"], lr=1e-9), tr, va, tmp_path / "c",
          seed=5, print_fn=logs.append, init_weights=tmp_path / "b" / "weights.pt")
    assert not any("shape anchors" in s for s in logs)
    c_model, _ = load_weights(tmp_path / "c" / "weights.pt")
    assert not changed_keys({"a": c_model.shape_anchor}, {"a": b.shape_anchor})


def _grown_from_trained(ds, tmp_path, model: dict):
    """Train a small network (run ``a``), then build one with the extra branches of ``model``
    initialised from it, and check that before any step it computes what ``a`` did (within float
    reordering noise: the grown layers multiply by zero-started columns).
    Returns (train split, val split, a, a's outputs on 6 validation frustums, that batch)."""
    from shape_detector.model.network import FrustumShapeNet
    from shape_detector.training.init_from import load_init

    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    train(_cfg(epochs=1), tr, va, tmp_path / "a", seed=3, print_fn=lambda s: None)
    a, _ = load_weights(tmp_path / "a" / "weights.pt")
    b = FrustumShapeNet(_cfg(model=model).model_config())
    load_init(b, a, None)
    a.eval(), b.eval()
    batch = TensorData(va, torch.device("cpu"), a.config.num_classes).batch(torch.arange(6), one_hot_mode="given")
    with torch.no_grad():
        oa, ob = a(batch["points"], batch["one_hot"]), b(batch["points"], batch["one_hot"])
    assert_outputs_close(ob, oa, ("center", "box_size", "box_heading", "cls_logits", "shape_raw", "seg_logits"))
    return tr, va, a, oa, batch


def test_box_context_branch_starts_as_the_init_model_and_then_learns(ds, tmp_path):
    """A model with the frustum-context branch, initialised from one without: before any step
    it computes what the init model did (the new inputs of the box head start at zero);
    a box fine-tune of ctx_mlp + box_head then changes only those."""
    ctx_model = dict(SMALL, box_context_widths=[16, 32])
    tr, va, a, _, _ = _grown_from_trained(ds, tmp_path, ctx_model)
    train(_cfg(epochs=1, tasks="box", model=ctx_model, trainable=["ctx_mlp", "box_head"], lr=0.01), tr, va,
          tmp_path / "b", seed=4, print_fn=lambda s: None, init_weights=tmp_path / "a" / "weights.pt")
    c, meta = load_weights(tmp_path / "b" / "weights.pt")
    assert c.config.box_context_widths == (16, 32)
    # a box-only fine-tune keeps the init's trained class head, and says so (the predictor scores
    # by class probability and runs the class-given second pass only for weights with one)
    assert set(meta["tasks"]) == {"box", "shape", "cls"}
    sa, sc = a.state_dict(), c.state_dict()
    changed = changed_keys(sa, sc)
    # only the box head moved; without the class task the class temperature is kept, not reset
    assert changed and all(k.startswith("box_head") for k in changed), changed
    assert any(not torch.all(v == 0) for k, v in sc.items() if k.startswith("ctx_mlp.") and k.endswith("weight"))
    with pytest.raises(ValueError, match="model config"):  # the branch may be added, not removed
        train(_cfg(epochs=1, model=SMALL), tr, va, tmp_path / "c", seed=4, print_fn=lambda s: None,
              init_weights=tmp_path / "b" / "weights.pt")


def test_shape_context_branch_starts_as_the_init_model_and_moves_only_the_shape(ds, tmp_path):
    """A model with the shape-context branch, initialised from one without, computes what
    the init did (the shape head's new inputs start at zero weights); a shape fine-tune of
    the shape branch then changes the primitives and nothing else: boxes, classes and masks stay
    unchanged. The branch reads the background: moving frustum points the mask leaves out
    changes the shape."""
    ctx_model = dict(SMALL, shape_context_widths=[16, 32])
    tr, va, a, oa, batch = _grown_from_trained(ds, tmp_path, ctx_model)
    train(_cfg(epochs=1, model=ctx_model, tasks="box,shape,cls", lr=0.01,
               trainable=["shape_ctx_mlp", "shape_mlp", "shape_head"]), tr, va, tmp_path / "b",
          seed=4, print_fn=lambda s: None, init_weights=tmp_path / "a" / "weights.pt")
    c, meta = load_weights(tmp_path / "b" / "weights.pt")
    assert c.config.shape_context_widths == (16, 32)
    # the class logits are the init's, so the class temperature is kept, not re-fitted
    assert meta["calibration"].get("kept")
    assert not changed_keys({"t": c.cls_temperature}, {"t": a.cls_temperature})
    sa, sc = a.state_dict(), c.state_dict()
    changed = changed_keys(sa, sc)
    assert changed and all(k.startswith(("shape_mlp", "shape_head", "shape_anchor")) for k in changed), changed
    c.eval()
    with torch.no_grad():
        oc = c(batch["points"], batch["one_hot"])
        assert_outputs_close(oc, oa, ("center", "box_size", "box_heading", "cls_logits", "seg_logits"))
        assert outputs_differ(oc["shape_raw"], oa["shape_raw"])
        # the background moved (the GT mask held fixed): the same box from the same object
        # points, another shape from what surrounds them
        fg = batch["seg"] > 0
        assert fg.any(1).all()
        moved = batch["points"].clone()
        moved[..., :3] = torch.where(fg.unsqueeze(-1), moved[..., :3], moved[..., :3] * 1.5 + 0.3)
        of = c(batch["points"], batch["one_hot"], fg_override=fg)
        om = c(moved, batch["one_hot"], fg_override=fg)
    assert_outputs_close(om, of, ("center", "box_size"))
    assert outputs_differ(om["shape_raw"], of["shape_raw"])
    with pytest.raises(ValueError, match="shape_branch"):
        ModelConfig.from_dict(dict(SMALL, shape_branch="shared", shape_context_widths=[8]))


def test_second_box_stage_starts_as_the_init_model_and_trains_alone(ds, tmp_path):
    """A model with the second box stage, initialised from one without, computes what
    the init did (its output layer starts at zero); a box fine-tune of box2_mlp +
    box2_head moves only those, and the refined box is what the weights then predict."""
    ref_model = dict(SMALL, box2_widths=[16, 32], box2_fc=[16])
    tr, va, a, oa, batch = _grown_from_trained(ds, tmp_path, ref_model)
    train(_cfg(epochs=2, tasks="box", model=ref_model, trainable=["box2_mlp", "box2_head"], lr=0.01), tr, va,
          tmp_path / "b", seed=4, print_fn=lambda s: None, init_weights=tmp_path / "a" / "weights.pt")
    c, meta = load_weights(tmp_path / "b" / "weights.pt")
    assert c.config.box2_widths == (16, 32) and set(meta["tasks"]) == {"box", "shape", "cls"}
    sa, sc = a.state_dict(), c.state_dict()
    assert not changed_keys(sa, sc)  # everything of the init is kept as it was
    c.eval()
    with torch.no_grad():
        oc = c(batch["points"], batch["one_hot"])
    assert_outputs_close({"center": oc["center_head"]}, oa, ["center"])  # the first box is the init's
    assert outputs_differ(oc["center"], oa["center"]) and outputs_differ(oc["box_size"], oa["box_size"])


def test_an_init_may_differ_in_its_point_counts_but_not_in_its_layers() -> None:
    """Fine-tuning at other point counts starts from the init's parameters unchanged (the counts
    shape no parameter); a different layer width is still refused."""
    from shape_detector.model.config import ModelConfig
    from shape_detector.model.network import FrustumShapeNet
    from shape_detector.training.init_from import load_init

    tuple_small = {k: tuple(v) if isinstance(v, list) else v for k, v in SMALL.items()}
    torch.manual_seed(0)
    a = FrustumShapeNet(ModelConfig(**tuple_small))
    b = FrustumShapeNet(ModelConfig(**dict(tuple_small, num_points=64, num_object_points=32)))
    load_init(b, a, None)
    assert b.config.num_points == 64 and b.config.num_object_points == 32
    assert not changed_keys(a.state_dict(), b.state_dict())
    wider = FrustumShapeNet(ModelConfig(**dict(tuple_small, cls_fc=(32,))))
    with pytest.raises(ValueError, match="cls_fc"):
        load_init(wider, a, None)


def test_a_teacher_adds_distillation_terms_and_must_match_the_heads(ds, tmp_path):
    tr, va = fds.split_by_frame(ds, 0.34, seed=0)
    train(_cfg(epochs=1), tr, va, tmp_path / "teacher", seed=3, print_fn=lambda s: None)
    logs = []
    distill = dict(distill_seg=1.0, distill_heading=1.0, distill_size=1.0, distill_cls=1.0)
    half = dict(SMALL, seg_widths=[8, 8, 16], box_widths=[8, 16])
    res = train(_cfg(epochs=1, model=half, teacher=str(tmp_path / "teacher" / "weights.pt"), loss_weights=distill),
                tr, va, tmp_path / "student", seed=4, print_fn=logs.append)
    assert any("distilling from" in s for s in logs)
    steps = json.loads((tmp_path / "student" / "log.json").read_text())["steps"]
    assert steps and all(k in steps[-1] for k in ("distill_seg", "distill_heading", "distill_cls"))
    assert res is not None
    _, meta = load_weights(tmp_path / "student" / "weights.pt")
    assert len(meta["teacher"]["sha256"]) == 64
    logs.clear()
    train(_cfg(epochs=1, model=half, teacher=str(tmp_path / "teacher" / "weights.pt"), loss_weights=distill,
               trainable=["shape_mlp", "shape_head"]), tr, va, tmp_path / "shape_only", seed=4, print_fn=logs.append,
          init_weights=tmp_path / "student" / "weights.pt")
    assert any("teacher not used" in s for s in logs)
    with pytest.raises(ValueError, match="num_heading_bins"):
        train(_cfg(epochs=1, model=dict(half, num_heading_bins=6), teacher=str(tmp_path / "teacher" / "weights.pt"),
                   loss_weights=distill),
              tr, va, tmp_path / "bad", seed=4, print_fn=lambda s: None)
