"""Parameter validation of the node, without ROS: every parameter's default is valid and
the values that made the node misbehave are refused with a reason naming the parameter."""

from __future__ import annotations

import math

import pytest

from shape_detector.node_params import PARAMETERS, validate, validate_all
from shape_detector.validation import check_choice, check_number, check_vector


def test_defaults_are_valid():
    assert validate_all({k: v.default for k, v in PARAMETERS.items()}) == []


def test_plan_defaults_match_the_library():
    from shape_detector.ar.margins import UNCERTAINTY
    from shape_detector.ar.planning import SQUEEZE

    assert PARAMETERS["plan_uncertainty"].default == UNCERTAINTY
    assert PARAMETERS["plan_squeeze"].default == SQUEEZE


@pytest.mark.parametrize("name, value", [
    ("depth_scale", -0.001), ("max_objects", 0), ("max_objects", -3), ("score_threshold", 1.5),
    ("score_threshold", -0.1), ("score_threshold", math.nan), ("sync_slop", math.inf), ("qos_depth", 0),
    ("stats_period", -1.0), ("warn_image_bytes", 0), ("max_objects", 2.5), ("refine", 1),
    ("up_source", "gyro"), ("precision", "fp16"), ("mirror_tta", "sometimes"), ("up", [0.0, 0.0, 0.0]),
    ("up", [0.0, 1.0]), ("imu_to_camera", [0.0, 0.0, math.nan, 1.0]), ("weights", 3),
])
def test_bad_values_are_refused_with_the_parameter_named(name, value):
    reason = validate(name, value)
    assert reason and name in reason


@pytest.mark.parametrize("name, value", [
    ("depth_scale", 0.0), ("depth_scale", 0.0001), ("max_objects", 1), ("score_threshold", 1.0),
    ("up", [0, 0, 2]), ("imu_to_camera", [0.0, 0.0, 0.0, 1.0]), ("precision", "bf16"), ("refine", False),
])
def test_good_values_pass(name, value):
    assert validate(name, value) is None


def test_unknown_parameters_are_not_ours_to_judge():
    assert validate("use_sim_time", True) is None


def test_helpers():
    assert check_number("x", 5, 0, 10, integer=True) is None
    assert "integer" in check_number("x", 5.0, 0, 10, integer=True)
    assert "number" in check_number("x", "5", 0, 10)
    assert "[0, 10]" in check_number("x", 11, 0, 10)
    assert check_choice("m", "a", ("a", "b")) is None and "one of" in check_choice("m", "c", ("a", "b"))
    assert check_vector("v", (1, 2, 3), 3) is None and "3 numbers" in check_vector("v", None, 3)
