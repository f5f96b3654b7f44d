"""Network shapes and the predictor's frame conventions (frustum frame F -> camera)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shape_detector.classes import CLASSES, class_id
from shape_detector.frustum import extract_frustum
from shape_detector.geometry import normalize, rot_z, rotation_to_heading, wrap_angle
from shape_detector.model.config import ModelConfig
from shape_detector.model.io import load_weights, save_weights
from shape_detector.model.network import FrustumShapeNet
from shape_detector.model.predictor import FrustumPrediction, FrustumPredictor

from test_model_scene import make_frame
from tolerances import ATOL, RTOL, outputs_differ
from small_net import save_small_weights




SMALL = dict(num_points=128, num_object_points=64, seg_widths=(16, 16, 32), seg_head_widths=(16,),
             tnet_widths=(16, 32), tnet_fc=(16,), box_widths=(16, 32), box_fc=(32,), shape_fc=(32,), cls_fc=(16,))


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return save_small_weights(tmp_path_factory.mktemp("w") / "w.pt", **SMALL)


def test_network_forward_shapes_single_frustum_eval():
    cfg = ModelConfig(**SMALL)
    net = FrustumShapeNet(cfg).eval()
    x = torch.randn(1, 100, 6)
    with torch.no_grad():
        out = net(x, torch.zeros(1, 10))
    assert out["seg_logits"].shape == (1, 100, 2)
    assert out["shape_raw"].shape == (1, cfg.num_primitives, 10)
    assert out["cls_logits"].shape == (1, 11)
    assert out["heading_scores"].shape == (1, 12) and out["size_res_norm"].shape == (1, 10, 3)
    # training mode with a batch works, and a frustum without foreground falls back to all points
    net.train()
    x = torch.randn(4, 100, 6)
    out = net(x, torch.eye(10)[:4], fg_override=torch.zeros(4, 100, dtype=torch.bool))
    assert torch.allclose(out["mask_mean"], x[..., :3].mean(1), atol=1e-6)
    assert int(out["fg_count"].sum()) == 0


def test_gather_object_points_uses_only_foreground():
    net = FrustumShapeNet(ModelConfig(**SMALL))
    xyz = torch.arange(2 * 10 * 3, dtype=torch.float32).view(2, 10, 3)
    fg = torch.zeros(2, 10, dtype=torch.bool)
    fg[0, [2, 5]] = True
    for random in (False, True):
        obj, mean, cnt = net.gather_object_points(xyz, fg, random)
        assert obj.shape == (2, 64, 3)
        rows0 = {tuple(r) for r in obj[0].tolist()}
        assert rows0 == {tuple(xyz[0, 2].tolist()), tuple(xyz[0, 5].tolist())}
        assert torch.allclose(mean[0], xyz[0, [2, 5]].mean(0))
        assert torch.allclose(mean[1], xyz[1].mean(0))  # no foreground -> all points
        assert cnt.tolist() == [2, 0]


def test_weights_round_trip_float16(weights, tmp_path):
    net, meta = load_weights(weights)
    assert meta["tasks"] == ["box", "cls", "shape"]
    assert net.config.num_points == 128 and not net.training
    net.cls_temperature.fill_(2.5)
    p = save_weights(net, tmp_path / "again.pt")
    net2, _ = load_weights(p)
    assert float(net2.cls_temperature) == pytest.approx(2.5)
    for (k, a), (_, b) in zip(net.state_dict().items(), net2.state_dict().items()):
        assert torch.allclose(a.float(), b.float(), atol=1e-2, rtol=1e-2), k


def test_predictor_outputs_in_camera_frame(weights):
    frame = make_frame(5, 2)
    pred = FrustumPredictor(weights, device="cpu", num_threads=1)
    frs = [
        extract_frustum(frame.rgb, frame.depth, frame.K, o.box2d, pred.num_points, up=frame.up, rng=np.random.default_rng(0))
        for o in frame.objects
    ]
    ids = [class_id(frame.objects[0].class_name)] + [None] * (len(frs) - 1)
    out = pred.predict(frs, ids)
    assert len(out) == len(frs)
    up = normalize(frame.up)
    for p, fr in zip(out, frs):
        assert isinstance(p, FrustumPrediction)
        assert p.class_name in CLASSES and p.class_probs.shape == (11,)
        assert abs(p.class_probs.sum() - 1) < 1e-5 and 0.0 <= p.score <= 1.0
        assert p.center.shape == (3,) and p.size.shape == (3,) and p.rotation.shape == (3, 3)
        assert np.allclose(p.rotation @ p.rotation.T, np.eye(3), atol=1e-6)
        assert np.allclose(p.rotation[:, 2], up, atol=1e-6)
        assert np.allclose(p.center, fr.R_cf @ p.center_F)
        assert abs(wrap_angle(rotation_to_heading(p.rotation, frame.up) - p.heading_U)) < 1e-6
        assert p.seg_prob.shape == (pred.num_points,) and p.num_points_valid == fr.valid
        assert 1 <= len(p.primitives) <= 6 and len(p.primitives) == len(p.primitives_canonical)
        for c, cc in zip(p.primitives, p.primitives_canonical):
            assert np.allclose(c.rotation @ c.rotation.T, np.eye(3), atol=1e-5)
            assert np.allclose(c.center, p.center + p.rotation @ cc.center, atol=1e-6)
    assert out[0].class_name == frame.objects[0].class_name
    assert pred.predict([], []) == []


def test_predictor_decodes_known_box_to_gt(weights):
    """A decoded frame-F box equal to the GT gives back the GT camera-frame box."""
    frame = make_frame(7, 1)
    obj = frame.objects[0]
    pred = FrustumPredictor(weights)
    fr = extract_frustum(frame.rgb, frame.depth, frame.K, obj.box2d, pred.num_points, up=frame.up)
    heading_u = rotation_to_heading(obj.rotation, frame.up)
    M = pred.config.num_primitives
    arr = {
        "probs": np.full((1, 11), 1 / 11), "seg_prob": np.zeros((1, pred.num_points)),
        "center": (fr.R_cf.T @ obj.center)[None], "heading": np.array([heading_u + fr.phi]),
        "size": obj.size[None], "cluster": np.array([class_id(obj.class_name)]), "fg_score": np.zeros(1),
        "prim_center": np.zeros((1, M, 3)), "prim_size": np.tile(obj.size / 2, (1, M, 1)),
        "prim_rotation": np.tile(np.eye(3), (1, M, 1, 1)),
    }
    p = pred._decode([fr], [None], arr)[0]
    assert np.allclose(p.center, obj.center, atol=1e-6)
    assert np.allclose(p.rotation, obj.rotation, atol=1e-6)
    assert abs(wrap_angle(p.heading_U - obj.heading)) < 1e-6
    assert np.allclose(p.primitives[0].center, obj.center, atol=1e-6)
    assert np.allclose(p.primitives[0].rotation, obj.rotation, atol=1e-6)


def test_bench_network_smoke(weights):
    from shape_detector.model.bench import bench_network

    r = bench_network(counts=(1, 2), weights=weights, num_threads=1, repeats=2, warmup=1, verbose=False)
    assert set(r["results"]) == {1, 2} and r["results"][2]["median_ms"] > 0


def test_weights_of_another_version_are_refused_with_the_reason(tmp_path):
    net = FrustumShapeNet(ModelConfig(**SMALL))
    blob = {"model_config": net.config.to_dict(), "state_dict": net.state_dict(), "meta": {}}
    torch.save(blob, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="format None"):
        load_weights(tmp_path / "old.pt")
    blob.update(format="shape_detector.frustum_shape_net", version=1)
    torch.save(blob, tmp_path / "v1.pt")
    with pytest.raises(ValueError, match="version 1"):
        load_weights(tmp_path / "v1.pt")
    save_weights(net, tmp_path / "new.pt")
    again, _ = load_weights(tmp_path / "new.pt")
    assert again.config == net.config


def test_fused_batchnorm_matches_eval_network():
    torch.manual_seed(1)
    net = FrustumShapeNet(ModelConfig(**SMALL))
    net.train()
    for _ in range(3):  # non-trivial running statistics
        net(torch.randn(8, 128, 6), torch.eye(10)[:8])
    net.eval()
    x, oh = torch.randn(3, 128, 6), torch.eye(10)[:3]
    with torch.no_grad():
        ref = net(x, oh)
        fused = net.fuse_batchnorm()
        got = fused(x, oh)
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in fused.modules())
    for k in ("seg_logits", "center", "heading_scores", "size_res_norm", "shape_raw", "cls_logits"):
        assert torch.allclose(ref[k], got[k], atol=1e-4, rtol=1e-4), k


def test_worker_threads_split_the_batch_without_changing_results(weights):
    """workers=2 runs chunks of the batch on two threads: same predictions, same order."""
    frames = [make_frame(s, 3) for s in (5, 6, 7)]
    serial = FrustumPredictor(weights, device="cpu", num_threads=1)
    split = FrustumPredictor(weights, device="cpu", num_threads=1, workers=2, min_chunk=2)
    frs, ids = [], []
    for f in frames:
        for o in f.objects:
            frs.append(extract_frustum(f.rgb, f.depth, f.K, o.box2d, serial.num_points, up=f.up,
                                       rng=np.random.default_rng(len(frs))))
            ids.append(None if len(frs) % 2 else class_id(o.class_name))
    assert len(frs) >= 4
    a, b = serial.predict(frs, ids), split.predict(frs, ids)
    assert split._pool is not None  # the batch really was split
    for p, q in zip(a, b):
        assert p.class_name == q.class_name and abs(p.score - q.score) < 1e-5
        np.testing.assert_allclose(p.center, q.center, atol=1e-5)
        np.testing.assert_allclose(p.size, q.size, atol=1e-5)
        np.testing.assert_allclose(p.seg_prob, q.seg_prob, atol=1e-5)
    # a batch smaller than two chunks stays on the calling thread
    assert len(split.predict(frs[:3], ids[:3])) == 3


def test_shared_mlp_forward_max_pools_like_forward_in_every_mode():
    """The inference shortcut (last layer's bias + ReLU after the max) changes nothing."""
    from shape_detector.model.pointnet import SharedMLP

    torch.manual_seed(2)
    mlp = SharedMLP(3, (8, 16, 32))
    x = torch.randn(4, 50, 3)
    mlp.train()
    mlp(torch.randn(4, 50, 3))  # running statistics
    for mode in ("train", "eval", "fused"):
        if mode == "eval":
            mlp.eval()
        if mode == "fused":
            for layer in mlp.layers:
                layer.fuse_batchnorm()
        with torch.no_grad():
            outs = mlp(x, return_all=True)
            pooled, kept = mlp.forward_max(x, keep=1)
            assert torch.allclose(pooled, outs[-1].amax(dim=1), atol=1e-5), mode
            assert torch.allclose(kept, outs[1], atol=1e-6), mode
            assert torch.allclose(mlp.forward_max(x), pooled)
    with pytest.raises(ValueError, match="keep"):
        mlp.forward_max(x, keep=2)


def test_bf16_precision_runs_and_stays_close(weights):
    frame = make_frame(5, 3)
    frs = [extract_frustum(frame.rgb, frame.depth, frame.K, o.box2d, 512, up=frame.up,
                           rng=np.random.default_rng(i)) for i, o in enumerate(frame.objects)]
    ids = [CLASSES.index(o.class_name) for o in frame.objects]
    ref = FrustumPredictor(weights, device="cpu", num_threads=1, backend="torch").predict(frs, ids)
    bf = FrustumPredictor(weights, device="cpu", num_threads=1, precision="bf16")
    got = bf.predict(frs, ids)
    assert bf.precision == "bf16" and len(got) == len(ref)
    # same class given, same points: the boxes agree to bfloat16's ~3 significant digits
    # (a heading or size bin may flip between near-equal scores, so compare the median)
    err = np.median([np.linalg.norm(a.center - b.center) for a, b in zip(ref, got)])
    assert err < 0.05
    with pytest.raises(ValueError, match="precision"):
        FrustumPredictor(weights, device="cpu", precision="fp16")


def test_auto_precision_uses_bf16_for_large_batches_on_amx_cpus(weights, monkeypatch):
    import shape_detector.model.devices as devices

    frame = make_frame(5, 3)
    frs = [extract_frustum(frame.rgb, frame.depth, frame.K, o.box2d, 512, up=frame.up,
                           rng=np.random.default_rng(i)) for i, o in enumerate(frame.objects)]
    pts = np.stack([f.points for f in frs] * 3)[: devices.AUTO_BF16_MIN_BATCH]
    oh = np.zeros((len(pts), len(CLASSES)), np.float32)
    fp = FrustumPredictor(weights, device="cpu", num_threads=1, backend="torch")
    bf = FrustumPredictor(weights, device="cpu", num_threads=1, precision="bf16", backend="torch")
    for amx in (True, False):
        monkeypatch.setattr(devices, "cpu_has_amx", lambda amx=amx: amx)
        auto = FrustumPredictor(weights, device="cpu", num_threads=1, precision="auto", backend="torch")
        assert auto.bf16_min_batch == (devices.AUTO_BF16_MIN_BATCH if amx else None)
        big = auto.forward_arrays(pts, oh)["center"]
        small = auto.forward_arrays(pts[:1], oh[:1])["center"]
        # large batches: the bf16 forward on an AMX CPU, fp32 elsewhere; one frustum: fp32
        chosen, other = (bf, fp) if amx else (fp, bf)
        np.testing.assert_allclose(big, chosen.forward_arrays(pts, oh)["center"], atol=ATOL, rtol=RTOL)
        assert outputs_differ(big, other.forward_arrays(pts, oh)["center"], atol=10 * ATOL)
        np.testing.assert_allclose(small, fp.forward_arrays(pts[:1], oh[:1])["center"], atol=ATOL, rtol=RTOL)


def _arrays(center, heading, size, probs, prim_center, prim_size, prim_rotation, heading_conf=None):
    B = len(center)
    return {
        "heading_conf": np.asarray(heading_conf if heading_conf is not None else [0.5] * B, np.float32),
        "center": np.asarray(center, np.float32), "heading": np.asarray(heading, np.float32),
        "size": np.asarray(size, np.float32), "cluster": np.zeros(B, np.float32),
        "probs": np.asarray(probs, np.float32), "seg_prob": np.full((B, 4), 0.5, np.float32),
        "fg_score": np.full(B, 0.7, np.float32), "prim_center": np.asarray(prim_center, np.float32),
        "prim_size": np.asarray(prim_size, np.float32), "prim_rotation": np.asarray(prim_rotation, np.float32),
    }


def test_merge_mirrored_hand_case():
    from shape_detector.model.predictor import merge_mirrored

    R45 = rot_z(np.pi / 4)
    prims = dict(prim_center=[[[0.1, 0.2, 0.0]]] * 3, prim_size=[[[0.5, 0.5, 0.5]]] * 3,
                 prim_rotation=[[np.eye(3)]] * 2 + [[R45]])
    # batch of 2 frustums (+ their 2 mirrored copies) -- and a third pair checks rotated primitives
    arr = _arrays(
        center=[[0.2, 3.0, 0.1], [0.0, 2.0, 0.0], [0, 2, 0], [-0.4, 3.2, 0.1], [0.0, 2.0, 0.0], [0, 2, 0]],
        # frustum 0: 0.3 and mirrored 0.5 -> 0.4; frustum 1: 0.3 and 0.5 + pi (opposite front) -> 0.4
        heading=[0.3, 0.3, 0.0, np.pi - 0.5, np.pi - (0.5 + np.pi), np.pi],
        size=[[1, 2, 3], [1, 1, 1], [1, 1, 1], [1.2, 2, 2.6], [1, 1, 1], [3, 1, 1]],
        probs=[[0.8, 0.2], [0.5, 0.5], [0.5, 0.5], [0.6, 0.4], [0.5, 0.5], [0.5, 0.5]],
        **{k: v * 2 for k, v in prims.items()},
    )
    out = merge_mirrored(arr)
    assert out["center"].shape == (3, 3)
    np.testing.assert_allclose(out["center"][0], [0.3, 3.1, 0.1], atol=1e-6)  # mirrored x = +0.4
    np.testing.assert_allclose(out["heading"][:2], [0.4, 0.4], atol=1e-6)
    np.testing.assert_allclose(out["size"][0], [1.1, 2.0, 2.8], atol=1e-6)
    np.testing.assert_allclose(out["probs"][0], [0.7, 0.3], atol=1e-6)
    # primitives: the first prediction's, stretched to the averaged size (x by 1.1, z by 2.8 / 3)
    np.testing.assert_allclose(out["prim_center"][0, 0], [0.11, 0.2, 0.0], atol=1e-6)
    np.testing.assert_allclose(out["prim_size"][0, 0], [0.55, 0.5, 0.5 * 2.8 / 3], atol=1e-6)
    # a primitive at 45 deg in a box stretched 2x along x: both its horizontal axes grow by |(2, 1)| / sqrt 2
    np.testing.assert_allclose(out["prim_size"][2, 0, :2], [0.5 * np.sqrt(2.5)] * 2, atol=1e-5)


def test_merge_mirrored_keeps_one_pass_when_they_disagree_about_the_axes():
    from shape_detector.model.predictor import merge_mirrored

    R = rot_z(0.3)
    arr = _arrays(
        center=[[0.2, 3.0, 0.1], [0.2, 3.0, 0.1], [-0.6, 3.4, 0.0], [-0.6, 3.4, 0.0]],
        # both frustums: 0.1 against a mirrored pi - (pi/2 + 0.1) = pi/2 - 0.1 -> 80 degrees apart
        heading=[0.1, 0.1, np.pi / 2 + 0.1, np.pi / 2 + 0.1],
        size=[[0.5, 1.0, 1.2]] * 2 + [[0.6, 0.9, 1.0]] * 2,
        probs=[[0.8, 0.2], [0.6, 0.4], [0.4, 0.6], [0.2, 0.8]],
        prim_center=[[[0.1, 0.2, 0.3]]] * 2 + [[[0.1, 0.25, -0.3]]] * 2,
        prim_size=[[[0.4, 0.5, 0.6]]] * 4,
        prim_rotation=[[np.eye(3)]] * 2 + [[R]] * 2,
        heading_conf=[0.9, 0.3, 0.5, 0.6],  # frustum 0 trusts its first pass, frustum 1 the mirrored one
    )
    out = merge_mirrored(arr)
    # frustum 0: the first pass whole (no 45-degree average)
    np.testing.assert_allclose(out["center"][0], [0.2, 3.0, 0.1], atol=1e-6)
    np.testing.assert_allclose(out["heading"][0], 0.1, atol=1e-6)
    np.testing.assert_allclose(out["size"][0], [0.5, 1.0, 1.2], atol=1e-6)
    np.testing.assert_allclose(out["prim_center"][0, 0], [0.1, 0.2, 0.3], atol=1e-6)
    # frustum 1: the mirrored pass whole, mapped back: x -> -x in F, heading pi - t, primitives y -> -y
    np.testing.assert_allclose(out["center"][1], [0.6, 3.4, 0.0], atol=1e-6)
    np.testing.assert_allclose(out["heading"][1], np.pi / 2 - 0.1, atol=1e-6)
    np.testing.assert_allclose(out["size"][1], [0.6, 0.9, 1.0], atol=1e-6)
    np.testing.assert_allclose(out["prim_center"][1, 0], [0.1, -0.25, -0.3], atol=1e-6)
    F = np.diag([1.0, -1.0, 1.0])
    np.testing.assert_allclose(out["prim_rotation"][1, 0], F @ R @ F, atol=1e-6)
    np.testing.assert_allclose(out["prim_size"][1, 0], [0.4, 0.5, 0.6], atol=1e-6)
    # class probabilities are still averaged
    np.testing.assert_allclose(out["probs"], [[0.6, 0.4], [0.4, 0.6]], atol=1e-6)


def test_mirror_tta_averages_the_two_passes(weights):
    from shape_detector.model.predictor import merge_mirrored

    frame = make_frame(6, 3)
    frs = [extract_frustum(frame.rgb, frame.depth, frame.K, o.box2d, 512, up=frame.up,
                           rng=np.random.default_rng(i)) for i, o in enumerate(frame.objects)]
    ids = [CLASSES.index(o.class_name) for o in frame.objects]
    pred = FrustumPredictor(weights, device="cpu", num_threads=1)
    got = pred.predict(frs, ids, mirror=True)
    pts = np.stack([f.points for f in frs]).astype(np.float32)
    flipped = pts.copy()
    flipped[..., 0] *= -1
    oh = np.zeros((len(frs), 10), np.float32)
    oh[np.arange(len(frs)), ids] = 1
    ref = merge_mirrored(pred.forward_arrays(np.concatenate([pts, flipped]), np.concatenate([oh, oh])))
    for j, (f, p) in enumerate(zip(frs, got)):
        np.testing.assert_allclose(p.center, f.R_cf @ ref["center"][j], atol=1e-5)
        np.testing.assert_allclose(p.size, ref["size"][j], atol=1e-6)
    plain = pred.predict(frs, ids)
    assert any(np.linalg.norm(a.center - b.center) > 1e-4 for a, b in zip(plain, got))  # it does something
