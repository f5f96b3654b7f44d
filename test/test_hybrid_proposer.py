"""The hybrid proposer: learned boxes take the edges of the geometric box they overlap."""

from __future__ import annotations

import numpy as np
import pytest

from shape_detector.proposals import Proposal
from shape_detector.proposals.hybrid import HybridProposer, fuse


def _p(box, score, source):
    return Proposal(box, None, score, source)


def test_matched_learned_box_takes_geometric_edges_and_learned_score():
    learned = [_p((100, 100, 220, 260), 0.95, "learned")]
    geo = [_p((105, 96, 210, 250), 0.80, "geometric")]
    out = fuse(learned, geo, match_iou=0.5)
    assert len(out) == 1
    assert out[0].box2d == pytest.approx((105, 96, 210, 250))
    assert out[0].score == pytest.approx(0.95)
    assert out[0].source == "hybrid"


def test_unmatched_boxes_kept_geometric_below_learned():
    learned = [_p((0, 0, 50, 50), 0.80, "learned")]
    geo = [_p((300, 300, 400, 400), 0.99, "geometric")]
    out = fuse(learned, geo, match_iou=0.5, unmatched_scale=0.7)
    assert [p.source for p in out] == ["learned", "geometric"]
    assert out[1].score == pytest.approx(0.693)
    assert len(fuse(learned, geo, keep_unmatched=False)) == 1


def test_each_geometric_box_serves_one_learned_box_best_first():
    geo = [_p((100, 100, 200, 200), 0.9, "geometric")]
    learned = [_p((102, 100, 200, 204), 0.80, "learned"), _p((100, 98, 198, 200), 0.90, "learned")]
    out = fuse(learned, geo, match_iou=0.5, keep_unmatched=False)
    by_score = {round(p.score, 2): p for p in out}
    assert by_score[0.9].source == "hybrid" and by_score[0.8].source == "learned"
    assert by_score[0.8].box2d == pytest.approx((102, 100, 200, 204))


def test_empty_inputs():
    geo = [_p((1, 1, 5, 5), 0.9, "geometric")]
    assert fuse([], [], 0.5) == []
    assert [p.source for p in fuse([], geo)] == ["geometric"]
    assert [p.source for p in fuse(geo, [])] == ["geometric"]


def test_hybrid_proposer_calls_both_and_needs_rgb():
    class Learned:
        def detect(self, rgb, depth):
            return [_p((10, 10, 60, 60), 0.9, "learned")]

    def geometric(depth, K, up=None, rgb=None):
        return "gravity", [_p((12, 10, 60, 58), 0.8, "geometric")]

    prop = HybridProposer(Learned(), geometric)
    grav, props = prop(np.ones((80, 80), np.float32), np.eye(3), rgb=np.zeros((80, 80, 3), np.uint8))
    assert grav == "gravity" and len(props) == 1 and props[0].box2d == pytest.approx((12, 10, 60, 58))
    with pytest.raises(ValueError, match="RGB"):
        prop(np.ones((80, 80), np.float32), np.eye(3))


def test_packaged_hybrid_proposer_keeps_geometric_edges_on_a_generated_frame():
    from shape_detector.proposals import get_proposer
    from shape_detector.synth.generate import SynthConfig, generate_frame

    f = generate_frame(10_004, SynthConfig(width=320, height=240))
    prop = get_proposer("hybrid")
    grav, props = prop(f.depth, f.K, rgb=f.rgb)
    _, geo = prop.geometric(f.depth, f.K, rgb=f.rgb)
    assert props and np.isfinite(grav.up).all()
    geo_boxes = {tuple(np.round(p.box2d, 3)) for p in geo}
    fused = [p for p in props if p.source == "hybrid"]
    assert fused and all(tuple(np.round(p.box2d, 3)) in geo_boxes for p in fused)
    assert [p.score for p in props] == sorted((p.score for p in props), reverse=True)


def test_detector_runs_on_hybrid_proposals():
    from shape_detector import ShapeDetector
    from shape_detector.synth.generate import SynthConfig, generate_frame

    f = generate_frame(10_004, SynthConfig(width=320, height=240))
    det = ShapeDetector(proposal_source="hybrid", score_threshold=0.0)
    objs = det.detect(f.rgb, f.depth, f.K)
    assert objs and all(np.all(np.isfinite(o.center)) for o in objs)
