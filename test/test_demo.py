"""``shape-detector demo`` on a walk-through bag (ground-truth detector), and the map top view."""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

import numpy as np
import pytest

from shape_detector import demo
from shape_detector.map_view import FREE_RGB, OCCUPIED_RGB, UNKNOWN_RGB, draw_map, side_by_side
from shape_detector.synth.walkthrough_bag import write_walkthrough_bag


def test_demo_writes_scene_picture_and_json(tmp_path, monkeypatch):
    from test_replay_scene import GTDetector

    bag = write_walkthrough_bag(tmp_path / "walk", frames=8, seed=1, width=160, height=120)
    import shape_detector.bags.detector_factory as factory

    monkeypatch.setattr(factory, "make_detector", lambda *a, **k: GTDetector(bag))
    p = argparse.ArgumentParser()
    demo.configure_parser(p)
    args = p.parse_args([str(bag), "--out", str(tmp_path / "out")])
    assert demo.main(args) == 0
    out = tmp_path / "out"
    for name in ("detections.mcap", "scene.json", "scene.png", "overlay.png", "summary.json"):
        assert (out / name).exists(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"]["frames"] == 8 and summary["scene"]["world_frame"] == "odom"
    import cv2

    pic = cv2.imread(str(out / "scene.png"))
    assert pic.shape[0] >= 480 and pic.shape[1] > pic.shape[0]  # frame beside the map


def test_demo_missing_bag(tmp_path):
    args = SimpleNamespace(bag=tmp_path / "nope", out=tmp_path / "o")
    assert demo.main(args) == 2


def test_map_top_view_cells_and_boxes():
    data = np.full((20, 40), -1, np.int8)  # 2 m x 1 m at 5 cm, origin (0, 0)
    data[:10, :] = 0  # y < 0.5 m seen free
    data[15:, 30:] = 100  # occupied corner at high x, high y
    grid = SimpleNamespace(resolution=0.05, origin=np.zeros(2), data=data)
    obj = SimpleNamespace(id=4, class_name="chair", center=np.array([0.5, 0.25, 0.4]), size=np.array([0.4, 0.2, 0.8]),
                          rotation=np.eye(3))
    img = draw_map(grid, [obj], height_px=200)
    assert img.shape == (200, 400, 3)
    # +y is up: the free rows (low y) are at the bottom, the occupied corner at the top right
    assert tuple(img[190, 390]) == FREE_RGB
    assert tuple(img[5, 395]) == OCCUPIED_RGB
    assert tuple(img[5, 5]) == UNKNOWN_RGB
    # the chair's footprint outline: x 0.3..0.7 m, y 0.15..0.35 m -> u 60..140, v 130..170
    col = img[150, 55:66]
    assert any(tuple(c) not in (FREE_RGB, UNKNOWN_RGB, OCCUPIED_RGB) for c in col)
    both = side_by_side(np.zeros((100, 50, 3), np.uint8), img)
    assert both.shape == (200, 400 + 100, 3)


@pytest.mark.parametrize("data", [np.zeros((0, 0), np.int8), np.full((1, 1), -1, np.int8)])
def test_map_top_view_degenerate_grids(data):
    img = draw_map(SimpleNamespace(resolution=0.05, origin=np.zeros(2), data=data), [], height_px=50)
    assert img.shape[0] == 50
