"""One declaration per setting: presets, validation, the generated YAML / docs / flags,
the post-processing pipeline built from the config, and ShapeDetector taking it."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import yaml

from shape_detector.config_cli import add_detector_flags, config_from_args
from shape_detector.config_docs import MARKDOWN_PATH, YAML_PATH, render_markdown, render_yaml
from shape_detector.detector_config import PRESETS, DetectorConfig, detector_specs, make_config, preset
from shape_detector.node_params import PARAMETERS
from shape_detector.postprocess import PostContext, build_pipeline
from shape_detector.settings import check
from shape_detector.types import Object3D


def test_every_setting_has_a_doc_and_a_valid_default():
    for name, spec in PARAMETERS.items():
        assert spec.doc and check(spec, spec.default) is None, name


def test_presets_are_valid_and_differ_where_documented():
    rt, acc = preset("realtime"), preset("accurate")
    assert rt == DetectorConfig()
    assert acc.max_objects > rt.max_objects and acc.precision == "fp32"
    assert rt.proposal_source == acc.proposal_source == "hybrid"
    assert set(PRESETS) == {"realtime", "accurate"}
    with pytest.raises(ValueError, match="preset"):
        preset("fastest")


@pytest.mark.parametrize("changes, word", [
    ({"max_objects": 0}, "max_objects"), ({"score_threshold": 2.0}, "score_threshold"),
    ({"point_fit": 0.5}, "point_fit"), ({"precision": "fp16"}, "precision"), ({"refine": 1}, "refine"),
    ({"nonsense": 1}, "nonsense"), ({"proposal_source": "yolo"}, "proposal_source"),
])
def test_invalid_values_are_refused_with_the_reason(changes, word):
    with pytest.raises(ValueError, match=word):
        make_config(**changes)


def test_all_problems_are_named_at_once():
    with pytest.raises(ValueError) as e:
        make_config(max_objects=-1, score_threshold=3.0)
    assert "max_objects" in str(e.value) and "score_threshold" in str(e.value)


def test_the_committed_yaml_and_docs_are_the_generated_ones():
    assert YAML_PATH.read_text() == render_yaml("realtime"), "run `shape-detector config --write`"
    assert MARKDOWN_PATH.read_text() == render_markdown(), "run `shape-detector config --write`"


def test_the_yaml_holds_every_node_parameter_with_its_default():
    values = yaml.safe_load(YAML_PATH.read_text())["/**"]["ros__parameters"]
    assert set(values) == set(PARAMETERS)
    for name, spec in PARAMETERS.items():
        assert values[name] == pytest.approx(spec.default), name


def test_accurate_yaml_differs_from_realtime_only_by_the_preset():
    acc = yaml.safe_load(render_yaml("accurate"))["/**"]["ros__parameters"]
    assert acc["max_objects"] == preset("accurate").max_objects


def _parse(argv: list[str], default: str = "accurate") -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_detector_flags(p, default)
    return p.parse_args(argv)


def test_flags_start_from_the_preset_and_apply_what_is_given():
    cfg = config_from_args(_parse([]))
    assert cfg == preset("accurate")
    cfg = config_from_args(_parse(["--preset", "realtime", "--max-objects", "4", "--no-free-space"]))
    assert cfg == preset("realtime", max_objects=4, free_space=False)


@pytest.mark.parametrize("argv", [["--max-objects", "-5"], ["--score-threshold", "2"], ["--precision", "x"],
                                  ["--max-objects", "two"]])
def test_bad_flags_are_refused_by_argparse(argv, capsys):
    with pytest.raises(SystemExit):
        _parse(argv)
    assert "must" in capsys.readouterr().err


def test_node_parameters_are_the_detector_settings_plus_the_nodes():
    assert set(detector_specs()) <= set(PARAMETERS)
    assert PARAMETERS["max_objects"].default == preset("realtime").max_objects


def test_pipeline_steps_follow_the_config():
    assert build_pipeline(DetectorConfig()).names == ["point_fit", "floor_snap", "free_space", "nms",
                                                      "primitive_snap"]
    off = make_config(point_fit=0.0, floor_snap=0.0, free_space=False, snap_primitives=False)
    assert build_pipeline(off).names == ["nms"]


def _box(x: float, score: float) -> Object3D:
    return Object3D("chair", score, [x, 0.0, 3.0], [0.5, 0.5, 0.8], np.eye(3))


def test_hooks_see_each_step_and_nms_skips_given_boxes():
    cfg = make_config(point_fit=0.0, floor_snap=0.0, free_space=False, snap_primitives=False, nms_decay=0.0)
    pipe = build_pipeline(cfg)
    seen: list[tuple[str, int]] = []
    objs = [_box(0.0, 0.9), _box(0.02, 0.8)]
    ctx = PostContext(np.ones((4, 4), np.float32), np.eye(3), np.array([0.0, -1.0, 0.0]), None, given_boxes=False)
    out = pipe.run(objs, ctx, hook=lambda name, o: seen.append((name, len(o))))
    assert seen == [("nms", 2), ("output", 1)] and len(out) == 1
    ctx.given_boxes = True
    assert len(pipe.run(objs, ctx)) == 2


def test_auto_workers_are_two_for_serial_calls_and_one_in_the_node_pipeline(monkeypatch):
    import os

    from shape_detector.detector_config import resolved_workers
    from shape_detector.node_params import PARAMETERS, detector_config

    assert preset("realtime").workers == 0 and preset("accurate").workers == 2
    assert resolved_workers(3) == 3 and resolved_workers(0, pipelined=True) == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert resolved_workers(0) == 2
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert resolved_workers(0) == 1
    p = {k: spec.default for k, spec in PARAMETERS.items()}
    assert detector_config(p, external=False).workers == 1  # pipeline on: auto resolves to one worker
    assert detector_config({**p, "pipeline": False}, external=False).workers == 0
    assert detector_config({**p, "workers": 2}, external=False).workers == 2
