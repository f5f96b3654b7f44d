"""Configuration of :class:`~shape_detector.model.network.FrustumShapeNet`.

The config is stored inside every checkpoint / weights file (``ModelConfig.to_dict``),
so a weights file is self-describing: :func:`shape_detector.model.io.load_weights`
rebuilds the exact network from it.

Widths were chosen for a CPU budget (>= 20 frames/s with 10 objects on 2 cores, see
:mod:`shape_detector.model.bench`); they are slimmer than Frustum PointNets v1
(seg 64-64-64-128-1024, box 128-128-256-512, 1024/2048 points).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

from ..classes import MEAN_SIZES, NUM_CLASSES

#: the network's arithmetic choices (see :class:`~shape_detector.model.predictor.FrustumPredictor`)
PRECISIONS = ("fp32", "bf16", "auto", "int8")


def _default_mean_sizes() -> list[list[float]]:
    return [[float(v) for v in row] for row in MEAN_SIZES]


@dataclass
class ModelConfig:
    """Hyper-parameters of the network (all sizes are channel counts unless noted).

    * ``num_points``: points per frustum fed to the segmentation PointNet (training
      data are extracted with this count; the network itself accepts any N).
    * ``num_object_points``: predicted-foreground points gathered (with replacement)
      for the T-Net and the box/shape PointNet.
    * ``use_color``: feed r g b to the segmentation net (the T-Net / box net see xyz only,
      as in Frustum PointNets).
    * ``num_heading_bins`` (NH), ``num_size_clusters`` (NS = class mean sizes),
      ``num_primitives`` (M cuboids of the shape head).
    * the shape head reads, besides the box feature, a small PointNet (``shape_widths``) over
      the object points expressed in the box's canonical frame and divided by its size (GT
      box, jittered, while training; the predicted box at inference).
    * ``prune_volume_frac``: at inference, primitives whose volume is below this share
      of the predicted box volume are dropped.
    * ``shape_anchors``: the shape head's raw output is added to a learnt per-class anchor
      row (``FrustumShapeNet.shape_anchor``, started from class templates of the GT parts,
      see :mod:`.shape_anchors`); the given class's, else the class head's argmax. On by default.
    * ``box_context_widths``: non-empty adds a PointNet (``ctx_mlp``) over *all* frustum
      points (xyz relative to the stage-1 centre, frame F, metres, plus the hard foreground
      mask as a 4th channel) whose max-pooled feature joins the box head's input: the floor
      and walls seen around the object bound its hidden extent. Empty: off.
    * ``box2_widths``: non-empty adds a second box stage (``box2_mlp`` +
      ``box2_head``, ``box2_fc``): a PointNet over all frustum points expressed in the
      first box's canonical frame and divided by its size (the box becomes the unit cube;
      clamped to +-4), with the hard mask as a 4th channel; from its feature, the box
      feature, the class one-hot and the first box's log size it regresses a residual centre
      (box axes, in box sizes), log size and heading. Empty: off.
    * ``shape_context_widths``: non-empty adds a PointNet (``shape_ctx_mlp``) over *all*
      frustum points in the shape branch's box frame divided by the box size (as the shape
      branch sees its object points; clamped to +-4), with the hard mask as a 4th channel;
      its max-pooled feature joins the shape head's input. The object's points say where it
      is; the rest of the frustum says where it is not (floor seen under a seat, wall seen
      through a shelf). Empty: off.

    The defaults are the shipped network (``shape_detector/weights/default.pt``); earlier
    training phases switch branches off (see ``shape_detector/training/recipes``).
    """

    num_points: int = 512
    num_object_points: int = 256
    num_classes: int = NUM_CLASSES
    num_heading_bins: int = 12
    num_size_clusters: int = NUM_CLASSES
    num_primitives: int = 6
    use_color: bool = True
    batchnorm: bool = True
    # segmentation PointNet: per-point MLP, the output of layer ``seg_local_index`` is the
    # local feature, the last layer is max-pooled to the global feature.
    seg_widths: tuple[int, ...] = (64, 64, 128, 256)
    seg_local_index: int = 1
    seg_head_widths: tuple[int, ...] = (128, 64)
    tnet_widths: tuple[int, ...] = (64, 128, 256)
    tnet_fc: tuple[int, ...] = (128, 64)
    box_widths: tuple[int, ...] = (64, 128, 256, 512)
    box_fc: tuple[int, ...] = (256, 128)
    box_context_widths: tuple[int, ...] = (64, 128, 256)
    box2_widths: tuple[int, ...] = (64, 128, 256)
    box2_fc: tuple[int, ...] = (128, 64)
    shape_fc: tuple[int, ...] = (256, 128)
    shape_widths: tuple[int, ...] = (64, 128, 256)
    shape_context_widths: tuple[int, ...] = (64, 128, 256)
    cls_fc: tuple[int, ...] = (128,)
    cls_dropout: float = 0.2
    mean_sizes: list[list[float]] = field(default_factory=_default_mean_sizes)
    prune_volume_frac: float = 0.002
    # primitive mapping, see shape_detector.model.primitives.primitive_params
    primitive_min_size_frac: float = 0.01
    shape_anchors: bool = True

    def primitive_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~shape_detector.model.primitives.primitive_params`."""
        return {"min_frac": float(self.primitive_min_size_frac)}

    @property
    def num_cls_outputs(self) -> int:
        """Classification head outputs: the classes plus background (last index)."""
        return self.num_classes + 1

    @property
    def in_channels(self) -> int:
        """Per-point input channels: xyz (m, frame F), plus rgb in [0, 1] with ``use_color``."""
        return 6 if self.use_color else 3

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples as lists); :meth:`from_dict` reads it back."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> ModelConfig:
        """Config from a dict of overrides of the defaults; unknown keys are refused."""
        d = dict(d or {})
        names = {f.name: f for f in fields(cls)}
        unknown = set(d) - set(names)
        if unknown:
            raise ValueError(f"unknown ModelConfig keys: {sorted(unknown)}")
        kw: dict[str, Any] = {}
        for k, v in d.items():
            if isinstance(v, list) and k.endswith(("widths", "_fc")):
                v = tuple(int(x) for x in v)
            kw[k] = v
        cfg = cls(**kw)
        if len(cfg.mean_sizes) != cfg.num_size_clusters:
            raise ValueError("mean_sizes must have num_size_clusters rows")
        return cfg
