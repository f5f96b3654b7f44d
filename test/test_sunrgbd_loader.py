"""The VoteNet-format SUN RGB-D loader on the one real frame shared beside the repo."""

from pathlib import Path

import numpy as np
import pytest

from shape_detector.frustum import backproject
from shape_detector.geometry import points_in_box

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "sunrgbd_sample"
pytestmark = pytest.mark.skipif(not SAMPLE.is_dir(), reason="shared SUN RGB-D sample not present")


@pytest.fixture(scope="module")
def frame():
    pytest.importorskip("scipy")
    from shape_detector.datasets.sunrgbd import load_frame

    return load_frame(SAMPLE, 1)


def test_frame_geometry(frame):
    assert frame.rgb.shape == (530, 730, 3) and frame.depth.shape == (530, 730)
    assert 0.6 < np.isfinite(frame.depth).mean() < 0.9
    np.testing.assert_allclose(np.linalg.norm(frame.up), 1.0)
    assert frame.up[1] < -0.9  # the Kinect is roughly level: up ~ optical -y
    np.testing.assert_allclose(frame.K[:2, 2], [364.0, 264.0])  # 1-based principal point shifted


def test_labels_match_points(frame):
    names = [o.class_name for o in frame.objects]
    assert names == ["bed", "night_stand", "dresser"]  # ottoman, lamp, dresser_mirror are not ours
    dresser = frame.objects[2]
    np.testing.assert_allclose(dresser.size[:2], [0.71, 1.56], atol=0.01)  # deep x wide
    np.testing.assert_allclose(dresser.rotation[:, 2], frame.up, atol=1e-9)
    pts = backproject(frame.depth, frame.K).reshape(-1, 3)
    pts = pts[np.isfinite(pts[:, 2])]
    for obj in frame.objects:
        inside = pts[points_in_box(pts, obj.center, obj.size, obj.rotation)]
        assert len(inside) > 300
        uv = inside @ frame.K.T
        uv = uv[:, :2] / uv[:, 2:]
        x1, y1, x2, y2 = obj.box2d
        # the points inside the 3D box project into the labelled 2D box
        assert uv[:, 0].min() >= x1 - 2 and uv[:, 0].max() <= x2 + 2
        assert uv[:, 1].min() >= y1 - 2 and uv[:, 1].max() <= y2 + 2
