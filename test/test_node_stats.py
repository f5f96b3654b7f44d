"""The node's bookkeeping without ROS: warnings rate-limited per distinct problem, latency
statistics that survive clocks jumping and mixed stamps."""

from __future__ import annotations

import numpy as np

from shape_detector.node_stats import (
    MAX_PLAUSIBLE_LATENCY_MS,
    NodeStats,
    WarningLimiter,
    percentiles,
    problem_key,
    stats_line,
)


def test_distinct_problems_of_one_kind_are_each_reported():
    lim = WarningLimiter()
    a = problem_key("skip:encoding", "frame skipped: image encoding 'yuv422' not supported")
    b = problem_key("skip:encoding", "frame skipped: image data shorter than height * step")
    assert a != b
    assert lim.admit(a, 0.0, 5.0) == 0
    assert lim.admit(b, 0.1, 5.0) == 0  # another reason of the same kind is not held back


def test_repeats_of_one_problem_are_held_back_and_counted():
    lim = WarningLimiter()
    k1 = problem_key("detector", "detector failed on frame 12.345: RuntimeError: boom")
    k2 = problem_key("detector", "detector failed on frame 99.001: RuntimeError: boom")
    assert k1 == k2  # only the stamp differs: one problem
    assert problem_key("w", "bad <object object at 0x7f89d1806250>") == problem_key("w", "bad <object object at 0x7e1>")
    assert lim.admit(k1, 0.0, 5.0) == 0
    assert lim.admit(k2, 1.0, 5.0) is None
    assert lim.admit(k2, 2.0, 5.0) is None
    assert lim.admit(k2, 5.5, 5.0) == 2
    assert lim.admit(k2, 6.0, float("inf")) is None


def test_once_only_and_bounded_memory():
    lim = WarningLimiter(max_keys=3)
    assert lim.admit("big|/a/image", 0.0, float("inf")) == 0
    assert lim.admit("big|/a/image", 1e6, float("inf")) is None
    for k in range(10):
        lim.admit(f"k{k}", 1.0, 5.0)
    assert len(lim._seen) == 3


def test_mixed_restamped_and_original_stamps_give_sane_percentiles():
    st = NodeStats()
    now_ms = 1.7e12  # a wall clock in ms
    for k in range(200):
        restamped = k % 2 == 0
        stamp_ms = now_ms - 80.0 if restamped else now_ms - 96_235_567_023.0  # the bag's original time
        st.frame_done(1, now_ms - stamp_ms, 85.0, 40.0)
    for _ in range(20):  # a clock that jumped back: stamps from the future
        st.frame_done(1, -5_000.0, 85.0, 40.0)
    s = st.snapshot()
    assert s["processed"] == 220 and s["implausible_stamps"] == 120
    assert 0 <= s["latency_p95_ms"] <= MAX_PLAUSIBLE_LATENCY_MS
    np.testing.assert_allclose(s["latency_p50_ms"], 80.0, atol=1e-6)
    line = stats_line({**s, "dropped": 3}, 2.5)
    assert "p95 80 ms" in line and "120 frames with stamps" in line and "96235567023" not in line


def test_only_implausible_stamps_fall_back_to_monotonic_latency():
    st = NodeStats()
    for _ in range(10):
        st.frame_done(0, -1e9, 120.0, None)
    line = stats_line({**st.snapshot(), "dropped": 0}, 1.0)
    assert "latency sync->publish p50 120 ms" in line and "stamp->publish" not in line
    assert st.take_period() == 10 and st.take_period() == 0


def test_percentiles_of_nothing():
    assert percentiles([]) is None
    assert percentiles([1.0, 3.0]) == (2.0, 2.9)
