"""The node-pipeline benchmark's bookkeeping: every frame goes through both stages in order,
the first stage's share of the first pass follows the previous frame's timings, and too few
frames are refused (no timing is asserted: speeds are the benchmark's to print)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from shape_detector.bench import _bench_pipelined

pytestmark = pytest.mark.timeout(60)


class StageLog:
    """A stand-in detector recording what each stage ran, with the timings of a frame whose
    first pass balances the stages at a share of one half."""

    def __init__(self) -> None:
        self.prepared: list[int] = []
        self.first: list[tuple[int, float]] = []
        self.finished: list[int] = []
        self.last_timing: dict[str, float] = {}

    def prepare(self, rgb, depth, K, up=None):
        self.prepared.append(int(rgb[0, 0, 0]))
        return int(rgb[0, 0, 0])

    def first_pass(self, prepared, share):
        self.first.append((prepared, share))

    def finish(self, prepared):
        self.finished.append(prepared)
        self.last_timing = {"proposals_ms": 5.0, "network_ms": 10.0, "refine_ms": 5.0}


def _frames(n: int) -> list:
    return [SimpleNamespace(rgb=np.full((2, 2, 3), i, np.uint8), depth=np.ones((2, 2), np.float32), K=np.eye(3))
            for i in range(n)]


def test_every_frame_passes_both_stages_in_order():
    det = StageLog()
    res = _bench_pipelined(det, _frames(12))
    assert det.finished == [0, *range(12)]  # the warm-up frame, then each frame once, in order
    assert det.prepared == [0, *range(12)]
    assert [f for f, _ in det.first] == list(range(12))
    assert all(s == pytest.approx(0.5, abs=0.2) for _, s in det.first)
    assert res["ms_per_frame"] > 0 and res["fps"] == pytest.approx(1e3 / res["ms_per_frame"])
    assert res["latency_ms_p95"] >= res["latency_ms_p50"] > 0


def test_split_prepare_runs_no_first_pass_in_the_first_stage():
    det = StageLog()
    _bench_pipelined(det, _frames(4), split="prepare")
    assert [s for _, s in det.first] == []


def test_a_single_frame_has_no_steady_state():
    with pytest.raises(ValueError, match="at least 2 frames"):
        _bench_pipelined(StageLog(), _frames(1))


def test_the_proposals_benchmark_times_the_default_built_in_proposer_too() -> None:
    from shape_detector.detector_config import preset
    from shape_detector.proposals.bench import bench_proposals

    res = bench_proposals(frames=1, repeats=1, verbose=False)
    assert res["total_ms_p50"] > 0 and res["proposals_per_frame"] > 0
    assert res["source"] == "synth"  # where the frames came from, not overwritten by the proposer's name
    source = preset("realtime").proposal_source
    if source == "geometric":
        assert "proposer" not in res
    else:  # the default's own proposer, as detect() calls it
        assert res["proposer"] == source and res["proposer_ms_p50"] > 0
        if source == "hybrid":
            assert res["learned_ms_p50"] > 0
