"""Post-processing of the network's boxes: an ordered pipeline of small geometric steps.

:func:`build_pipeline` builds it from a :class:`~shape_detector.detector_config.DetectorConfig`:
grow boxes to their segmented points (:mod:`.point_fit`), put them on the measured floor
(:mod:`.floor`), shrink them out of seen-through space (:mod:`.free_space`), 3D NMS over
built-in proposals (:mod:`.nms`), align primitives with their box (:mod:`.primitive_snap`).
"""

from .pipeline import Hook, Pipeline, PostContext, Step, build_pipeline

__all__ = ["Hook", "Pipeline", "PostContext", "Step", "build_pipeline"]
