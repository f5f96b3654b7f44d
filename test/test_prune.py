"""Structured pruning (training/prune.py): channel bookkeeping, scores, CLI."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from shape_detector.model.config import ModelConfig  # noqa: E402
from shape_detector.model.network import FrustumShapeNet  # noqa: E402
from shape_detector.training.prune import PRUNABLE, channel_scores, prune_network  # noqa: E402

SMALL = dict(num_points=128, num_object_points=64, seg_widths=(16, 16, 32, 48), seg_head_widths=(32, 16),
             tnet_widths=(16, 40), tnet_fc=(32,), box_widths=(16, 32, 56), box_fc=(32,), box_context_widths=(16, 36),
             box2_widths=(16, 44), box2_fc=(32,), shape_widths=(16, 28), shape_context_widths=(16, 24),
             shape_fc=(32,), cls_fc=(32,))


def _net() -> FrustumShapeNet:
    """A small random network with every branch and non-trivial BatchNorm statistics, eval mode."""
    torch.manual_seed(0)
    net = FrustumShapeNet(ModelConfig(**SMALL))
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.normal_(0.0, 0.2)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.normal_(0.0, 0.2)
    return net.eval()


def _inputs(b: int = 6) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    pts = rng.normal(0.0, 0.5, (b, SMALL["num_points"], 6)).astype(np.float32)
    pts[..., 2] += 3.0
    return pts, np.arange(b) % 10


def _outputs(net: FrustumShapeNet, pts: np.ndarray, cls: np.ndarray) -> dict[str, torch.Tensor]:
    one_hot = torch.zeros(len(pts), 10)
    one_hot[torch.arange(0, len(pts), 2), torch.as_tensor(cls[::2])] = 1.0
    with torch.no_grad():
        return net(torch.as_tensor(pts), one_hot, random_gather=False)


def _assert_same(a: dict, b: dict) -> None:
    for k in ("seg_logits", "center", "box_heading", "box_size", "cls_logits", "shape_raw"):
        torch.testing.assert_close(a[k], b[k], atol=1e-4, rtol=1e-4, msg=k)


def test_keeping_every_channel_changes_nothing():
    net = _net()
    pts, cls = _inputs()
    scores = channel_scores(net, pts, cls)
    assert set(scores) == set(PRUNABLE)
    full = {n: getattr(net, n).out_channels for n in PRUNABLE}
    _assert_same(_outputs(net, pts, cls), _outputs(prune_network(net, full, scores), pts, cls))


def test_dead_channels_score_zero_and_pruning_them_changes_nothing():
    """A last-layer channel that ReLU always zeroes carries nothing to its readers: it scores 0,
    and pruning every such channel (a forced one, and those random weights leave dead) from
    every PointNet leaves each output as it was."""
    net = _net()
    with torch.no_grad():
        for n in PRUNABLE:
            getattr(net, n).layers[-1].bn.bias[3] = -1e4
    pts, cls = _inputs()
    scores = channel_scores(net, pts, cls)
    widths = {}
    for n in PRUNABLE:
        assert float(scores[n][3]) == 0.0 and bool((scores[n] >= 0).all())
        widths[n] = int((scores[n] > 0).sum())
        assert 0 < widths[n] < getattr(net, n).out_channels
    pruned = prune_network(net, widths, scores)
    for n, key in PRUNABLE.items():
        assert getattr(pruned, n).out_channels == widths[n]
        assert list(getattr(pruned.config, key))[-1] == widths[n]
    assert sum(p.numel() for p in pruned.parameters()) < sum(p.numel() for p in net.parameters())
    _assert_same(_outputs(net, pts, cls), _outputs(pruned, pts, cls))


def test_pruning_live_channels_changes_the_outputs_and_keeps_the_best():
    net = _net()
    pts, cls = _inputs()
    scores = channel_scores(net, pts, cls)
    pruned = prune_network(net, {"box_mlp": 28}, scores)
    best = torch.sort(torch.argsort(scores["box_mlp"], descending=True)[:28]).values
    old = net.box_mlp.layers[-1].linear.weight
    torch.testing.assert_close(pruned.box_mlp.layers[-1].linear.weight, old[best])
    a, b = _outputs(net, pts, cls), _outputs(pruned, pts, cls)
    assert not torch.allclose(a["cls_logits"], b["cls_logits"], atol=1e-4)


@pytest.mark.parametrize("widths", [{"nope": 4}, {"box_mlp": 0}, {"box_mlp": 57}])
def test_bad_widths_are_refused(widths):
    net = _net()
    pts, cls = _inputs(2)
    with pytest.raises(ValueError):
        prune_network(net, widths, channel_scores(net, pts, cls))


def test_a_folded_network_is_refused():
    import copy

    net = _net()
    pts, cls = _inputs(2)
    scores = channel_scores(net, pts, cls)
    with pytest.raises(ValueError, match="folded"):
        prune_network(copy.deepcopy(net).fuse_batchnorm(), {"box_mlp": 40}, scores)


def test_cli_writes_a_loadable_pruned_weights_file(tmp_path, capsys):
    from shape_detector.cli import main
    from shape_detector.model.io import load_weights, save_weights
    from shape_detector.training.frustum_dataset import save

    src = save_weights(_net(), tmp_path / "small.pt", meta={"tasks": ["box", "cls", "shape"], "val": {"box_iou": 0.5}})
    pts, cls = _inputs(8)
    data = save({"points": pts, "class_id": cls.astype(np.int64)}, tmp_path / "frustums.npz")
    out = tmp_path / "pruned.pt"
    assert main(["prune", "--weights", str(src), "--data", str(data), "--out", str(out),
                 "--width", "box_mlp=40", "--width", "seg_mlp=32"]) == 0
    model, meta = load_weights(out)
    assert model.box_mlp.out_channels == 40 and model.seg_mlp.out_channels == 32
    assert meta["pruned_from"]["widths"] == {"box_mlp": 40, "seg_mlp": 32}
    assert meta["tasks"] == ["box", "cls", "shape"] and "val" not in meta
    assert "box_mlp: 56 -> 40 channels" in capsys.readouterr().out
    assert main(["prune", "--weights", str(src), "--data", str(data), "--out", str(out), "--width", "box_mlp"]) == 2


def test_scores_are_the_same_with_batchnorm_folded():
    """Folded (inference) networks pool without calling their last layer; the scores still read
    the pooled features, and the readers' BatchNorm scale is then inside their weights."""
    import copy

    net = _net()
    pts, cls = _inputs()
    plain = channel_scores(net, pts, cls)
    folded = channel_scores(copy.deepcopy(net).fuse_batchnorm(), pts, cls)
    for n in PRUNABLE:
        torch.testing.assert_close(folded[n], plain[n], atol=1e-4, rtol=1e-3, msg=n)
