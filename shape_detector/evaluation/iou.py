"""Box IoUs now live in :mod:`shape_detector.box_iou` (below everything that uses them)."""

from ..box_iou import (  # noqa: F401
    VERTICAL_TOL,
    box2d_iou,
    box2d_iou_matrix,
    box3d_iou,
    box3d_iou_grid,
    box_prism,
    clip_convex,
    iou_matrix,
    polygon_area,
    vertical_axis,
)
