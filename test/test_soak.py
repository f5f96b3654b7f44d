"""The soak benchmark's bookkeeping (the run itself is ``shape-detector bench soak``)."""

from __future__ import annotations

import math
import os

from shape_detector.node_bench import rss_mb
from shape_detector.soak import _summarise, in_stamp_order, node_totals

LOG = ("[INFO] [1.0] [sd]: 3.0 frames/s; totals: 10 synced, 7 processed, 3 dropped (busy), 0 skipped\n"
       "[shape_detector] at exit: 2.0 frames/s; totals: 120 synced, 80 processed, 40 dropped (busy), 0 skipped\n")


def test_totals_come_from_the_last_statistics_line():
    assert node_totals(LOG) == (120, 80, 40)
    assert node_totals("nothing") == (0, 0, 0)


def test_stamp_order_is_strict():
    assert in_stamp_order([1, 2, 5]) and in_stamp_order([])
    assert not in_stamp_order([1, 3, 3]) and not in_stamp_order([2, 1])


def test_rss_of_this_process_and_of_none():
    assert rss_mb(os.getpid()) > 1.0
    assert math.isnan(rss_mb(2**22 + 12345))


def test_verdict_needs_bounded_memory_order_and_a_clean_exit():
    rss = [(0.0, 500.0), (60.0, 510.0), (600.0, 540.0)]
    rec = [(0, 1, "c", 1), (0, 2, "c", 1)]
    ok = _summarise({"node_exit_code": 0}, rss, rec, LOG)
    assert ok["ok"] and ok["rss_mb_minute1"] == 510.0 and abs(ok["rss_growth"] - 30 / 510) < 1e-9
    assert ok["published"] == 2 and ok["processed"] == 80
    assert not _summarise({"node_exit_code": 0}, [(60.0, 500.0), (600.0, 600.0)], rec, LOG)["ok"]  # +20 %
    assert not _summarise({"node_exit_code": 0}, rss, rec[::-1], LOG)["ok"]  # out of order
    assert not _summarise({"node_exit_code": -9}, rss, rec, LOG)["ok"]
