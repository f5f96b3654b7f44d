"""The traced inference graphs give the eager forward's outputs (within float reordering noise), per variant."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shape_detector.model.config import ModelConfig
from shape_detector.model.network import FrustumShapeNet
from shape_detector.model.predictor import FrustumPredictor
from shape_detector.model.traced import OUTPUT_KEYS, TracedForward, inference_outputs

from tolerances import ATOL, RTOL, assert_outputs_close


@pytest.fixture(scope="module")
def model() -> FrustumShapeNet:
    torch.manual_seed(0)
    cfg = ModelConfig(num_points=64, num_object_points=32)
    net = FrustumShapeNet(cfg)
    # non-trivial BatchNorm statistics, then folded as at inference
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
    return net.eval().fuse_batchnorm()


def _inputs(b: int, n: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(b, n, 6, generator=g)
    pts[..., 2] += 3.0
    oh = torch.zeros(b, 10)
    oh[: b // 2, 3] = 1.0  # half class-given, half class-agnostic
    return pts, oh


@pytest.mark.parametrize("bf16", [False, True])
def test_traced_graphs_equal_the_eager_forward_for_any_batch(model, bf16):
    traced = TracedForward(model)
    eager = TracedForward(model, enabled=False)
    with torch.inference_mode():
        for b in (3, 1, 7):  # traced on the first batch size, reused for the others
            pts, oh = _inputs(b, seed=b)
            got, want = traced(pts, oh, bf16=bf16), eager(pts, oh, bf16=bf16)
            assert set(got) == set(OUTPUT_KEYS)
            for k in OUTPUT_KEYS:
                assert got[k].shape[0] == b
                torch.testing.assert_close(got[k], want[k], rtol=RTOL, atol=ATOL, msg=k)
            # the second pass over the same points with the class given reuses the features
            oh2 = torch.zeros_like(oh)
            oh2[:, 5] = 1.0
            cache = (want["seg_glob"], want["seg_local"])
            got2, want2 = traced(pts, oh2, cache, bf16=bf16), eager(pts, oh2, cache, bf16=bf16)
            full = eager(pts, oh2, bf16=bf16)
            for k in OUTPUT_KEYS:
                torch.testing.assert_close(got2[k], want2[k], rtol=RTOL, atol=ATOL, msg=k)
                torch.testing.assert_close(got2[k], full[k], rtol=RTOL, atol=ATOL, msg=k)
    assert traced.traced == 2 and eager.traced == 0  # one graph per variant (plain, cached)
    want_dtype = torch.bfloat16 if bf16 else torch.float32
    assert want["seg_local"].dtype == want_dtype  # the forward ran in the precision asked for


def test_inference_outputs_decode_the_forward(model):
    pts, oh = _inputs(4)
    with torch.inference_mode():
        out = dict(zip(OUTPUT_KEYS, inference_outputs(model, pts, oh)))
        raw = model(pts, oh, random_gather=False)
    probs = torch.softmax(raw["cls_logits"] / model.cls_temperature, 1)
    torch.testing.assert_close(out["probs"], probs)
    torch.testing.assert_close(out["probs"].sum(1), torch.ones(4))
    assert out["seg_prob"].shape == (4, 64) and out["prim_rotation"].shape == (4, model.config.num_primitives, 3, 3)
    torch.testing.assert_close(out["center"], raw["center"])


def test_tracing_failure_falls_back_to_eager_with_a_warning(model, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("no tracing here")

    monkeypatch.setattr(torch.jit, "trace", broken)
    traced = TracedForward(model)
    pts, oh = _inputs(2)
    with torch.inference_mode(), pytest.warns(UserWarning, match="running eagerly"):
        got = traced(pts, oh)
    with torch.inference_mode():
        want = TracedForward(model, enabled=False)(pts, oh)
        again = traced(pts, oh)  # no second attempt, no second warning
    assert not traced.enabled and traced.traced == 0
    for k in OUTPUT_KEYS:
        torch.testing.assert_close(got[k], want[k], rtol=RTOL, atol=ATOL)
        torch.testing.assert_close(again[k], want[k], rtol=RTOL, atol=ATOL)


def test_predictor_traced_and_eager_predictions_agree():
    from shape_detector.frustum import Frustum

    rng = np.random.default_rng(1)
    frustums = []
    for _ in range(5):
        pts = np.concatenate([rng.normal(0, 0.4, (512, 3)) + [0, 0, 3], rng.uniform(0, 1, (512, 3))], 1)
        frustums.append(Frustum(points=pts.astype(np.float32), pixel_index=np.arange(512), valid=512, phi=0.0,
                                R_cu=np.eye(3)))
    a = FrustumPredictor(None, workers=2, backend="torch")
    b = FrustumPredictor(None, workers=2, trace=False)
    ids = [None, 2, None, 7, 0]
    first_a = a.predict(frustums, ids, keep_features=True)
    first_b = b.predict(frustums, ids, keep_features=True)
    for pa, pb in zip(a.refine(frustums, first_a), b.refine(frustums, first_b)):
        assert pa.class_name == pb.class_name and pa.score == pytest.approx(pb.score, abs=ATOL)
        assert_outputs_close(vars(pa), vars(pb), ("center", "size", "seg_prob"))
        assert len(pa.primitives) == len(pb.primitives)
    assert a._forward.traced >= 1 and b._forward.traced == 0


@pytest.mark.parametrize("precision, graphs", [("fp32", 2), ("bf16", 2)])
def test_warm_up_traces_every_graph_a_frame_needs(precision, graphs):
    from shape_detector.frustum import Frustum

    pred = FrustumPredictor(None, precision=precision, workers=1, backend="torch")
    pred.warm_up()
    assert pred._forward.traced == graphs  # first pass and the feature-reusing second pass
    rng = np.random.default_rng(2)
    frustums = [
        Frustum(points=rng.normal(0, 1, (512, 6)).astype(np.float32), pixel_index=np.arange(512), valid=512,
                phi=0.0, R_cu=np.eye(3))
        for _ in range(3)
    ]
    first = pred.predict(frustums, [None] * 3, keep_features=True)
    pred.refine(frustums, first)
    assert pred._forward.traced == graphs  # nothing left to trace on a real frame
