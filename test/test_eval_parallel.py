"""Evaluations over seeds in worker processes: same results in seed order as here, a worker's
failure raised, the CLIs' --processes."""

from __future__ import annotations

import os

import numpy as np
import pytest

from shape_detector.evaluation.parallel import map_seeds

pytestmark = pytest.mark.timeout(180)


def seed_info(seed: int, detector=None, scale: float = 1.0) -> tuple[int, float, int, bool]:
    """Module level, so that the workers can run it."""
    if seed < 0:
        raise ValueError(f"bad seed {seed}")
    return seed, scale * seed, os.getpid(), detector is None


def test_results_come_back_in_seed_order_from_workers():
    seeds = [5, 3, 9, 1]
    here = list(map_seeds(seed_info, seeds, None, 1, scale=2.0))
    there = list(map_seeds(seed_info, seeds, None, 2, scale=2.0))
    assert [r[:2] for r in here] == [r[:2] for r in there] == [(5, 10.0), (3, 6.0), (9, 18.0), (1, 2.0)]
    assert {r[2] for r in here} == {os.getpid()} and os.getpid() not in {r[2] for r in there}
    assert all(r[3] for r in here + there)  # no config: no detector
    with pytest.raises(ValueError, match="bad seed -1"):
        list(map_seeds(seed_info, [2, -1], None, 2))


def test_a_given_detector_is_used_here():
    marker = object()
    assert [r[3] for r in map_seeds(seed_info, [1, 2], None, 1, marker)] == [False, False]


def test_evaluate_ar_true_map_in_two_processes_matches_one(capsys):
    import argparse

    from shape_detector.evaluation import ar_cli

    p = argparse.ArgumentParser()
    ar_cli.configure_parser(p)
    base = ["--gt-map", "--seeds", "101", "102", "--frames", "3", "--width", "96", "--height", "72",
            "--rays", "200", "--points", "200", "--pairs", "5"]
    means = []
    for n in ("1", "2"):
        assert ar_cli.main(p.parse_args(base + ["--processes", n])) == 0
        out = capsys.readouterr().out
        means.append([line for line in out.splitlines() if ":" in line and "seed" not in line])
    assert means[0] == means[1] and len(means[0]) > 5
    assert ar_cli.main(p.parse_args(base + ["--processes", "0"])) == 2


def test_collect_in_workers_equals_collect_here():
    from shape_detector.detector_config import preset
    from shape_detector.evaluation.scene_eval import collect

    cfg = preset("realtime", workers=1)
    here = collect([7, 8], 2, 96, 72, config=cfg)
    there = collect([7, 8], 2, 96, 72, config=cfg, processes=2)
    assert sum(len(d) for s in here for d in s.detections) >= 3
    for a, b in zip(here, there):
        assert a.seed == b.seed and len(a.detections) == len(b.detections)
        for da, db in zip(a.detections, b.detections):
            assert [o.class_name for o in da] == [o.class_name for o in db]
            for oa, ob in zip(da, db):
                np.testing.assert_allclose(oa.center, ob.center, atol=1e-3)


def test_pooled_shares_weigh_walkthroughs_by_their_rays_and_pairs():
    from shape_detector.evaluation.ar_cli import pooled_shares

    rows = [{"ray_within_5cm": 1.0, "rays_used": 300.0, "plan_found": 1.0, "plan_pairs": 40.0, "plan_clear": 0.5},
            {"ray_within_5cm": 0.0, "rays_used": 100.0, "plan_found": 0.0, "plan_pairs": 10.0,
             "plan_clear": float("nan")}]
    p = pooled_shares(rows)
    assert p == {"ray_within_5cm": 0.75, "plan_found": 0.8, "plan_clear": 0.5}
