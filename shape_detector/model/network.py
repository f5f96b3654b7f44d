"""FrustumShapeNet: Frustum PointNets v1 with a cuboid shape head and a classification head.

Pipeline for a batch of frustums (points in the frustum frame ``F``, see
:mod:`shape_detector.frustum`):

1. **instance segmentation** PointNet over all ``N`` points (xyz [+ rgb]); per-point
   logits from [local feature, global feature, class one-hot];
2. hard mask from the logits; ``num_object_points`` predicted-foreground points are
   gathered (with replacement; all points if none is foreground) and centred on the
   mean of the masked points;
3. **T-Net** regresses a residual centre (stage-1 centre = mask mean + residual);
4. **box PointNet** on the points relative to the stage-1 centre -> global feature;
   (a) amodal box head: centre residual, ``NH`` heading bins + normalised residuals,
   ``NS`` size clusters + normalised residuals (see :mod:`.box_coder`); with
   ``box_context_widths`` it also gets a context PointNet's feature over every frustum
   point around the stage-1 centre with the hard mask as a channel (what surrounds the object);
   with ``box2_widths`` a second box stage (:meth:`FrustumShapeNet.second_box_stage`) refines
   that box from every frustum point seen in its own canonical frame;
   (b) shape head: ``M`` cuboid primitives in the canonical object frame (see
   :mod:`.primitives`), from the box feature and a small
   PointNet over the object points in the canonical frame of a box (``shape_box``: the GT
   box while training, the predicted box otherwise), divided by the box size, and (with
   ``shape_context_widths``) a PointNet over every frustum point in that frame with the
   hard mask as a 4th channel;
   (c) classification head over [segmentation global feature, box feature] (no class
   one-hot input), ``num_classes + 1`` logits, background last; a temperature buffer
   ``cls_temperature`` (set by calibration after training) scales them at inference.
   With ``shape_anchors`` the shape head's raw output is a residual added to a per-class
   anchor row (:mod:`.shape_anchors`): the given class's, else the class head's argmax.

The class one-hot may be all zeros (class-agnostic proposals); training drops it at random.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .box_coder import box_head_channels, decode_heading, decode_size, gather_bin, split_box_head
from .config import ModelConfig
from .pointnet import FCHead, SharedMLP


def to_box_axes(d: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Offsets ``d`` (B,N,3) in frame F expressed in the axes of boxes with yaw ``heading``
    (B,) about F's z: ``R_z(-heading) d``."""
    c, s = torch.cos(heading).unsqueeze(1), torch.sin(heading).unsqueeze(1)
    return torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)


def to_unit_box(p: torch.Tensor, center: torch.Tensor, heading: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """Points ``p`` (B,N,3, frame F) in the canonical frame of boxes (``center`` (B,3),
    ``heading`` (B,), ``size`` (B,3)) divided by the box size (at least 2 cm): the box
    becomes the unit cube ``[-0.5, 0.5]^3``."""
    return to_box_axes(p - center.unsqueeze(1), heading) / size.clamp_min(0.02).unsqueeze(1)


class FrustumShapeNet(nn.Module):
    """Frustum PointNets v1 with cuboid-shape and class heads (see the module docstring); points
    (B, N, C) in the frustum frame F (m), class one-hot (B, num_classes) -> a dict of outputs."""

    #: the network's parts by name, each a set of its child modules / parameters: training
    #: phases say which parts train (the rest is frozen) by these names
    MODULE_GROUPS: dict[str, tuple[str, ...]] = {
        "seg": ("seg_mlp", "seg_head_local", "seg_head_global", "seg_head_bn", "seg_head_mlp", "seg_out"),
        "seg_head": ("seg_head_local", "seg_head_global", "seg_head_bn", "seg_head_mlp", "seg_out"),
        "tnet": ("tnet_mlp", "tnet_head"),
        "box": ("box_mlp", "box_head"),
        "box_head": ("box_head",),
        "box_context": ("ctx_mlp",),
        "box2": ("box2_mlp", "box2_head"),
        "shape": ("shape_mlp", "shape_head", "shape_anchor"),
        "shape_context": ("shape_ctx_mlp",),
        "cls": ("cls_head",),
    }
    #: children that reach only the primitives (none of the segmentation, box or class outputs)
    SHAPE_ONLY = frozenset({"shape_mlp", "shape_ctx_mlp", "shape_head", "shape_anchor"})
    #: children whose parameters never reach ``cls_logits``: the class head reads only the
    #: segmentation and box PointNets' global features (and the mask decides the box net's
    #: points), so training only these leaves the class probabilities as they were
    OFF_CLASS_PATH = frozenset({"shape_mlp", "shape_ctx_mlp", "shape_head", "shape_anchor", "box_head", "ctx_mlp",
                                "box2_mlp", "box2_head"})

    def __init__(self, config: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or ModelConfig()
        nc = cfg.num_classes
        bn = cfg.batchnorm
        # 1. segmentation
        self.seg_mlp = SharedMLP(cfg.in_channels, cfg.seg_widths, bn)
        local_c = int(cfg.seg_widths[cfg.seg_local_index])
        global_c = int(cfg.seg_widths[-1])
        h0 = int(cfg.seg_head_widths[0])
        # first head layer split so the per-frustum part (global + one-hot) is computed once
        self.seg_head_local = nn.Linear(local_c, h0, bias=False)
        self.seg_head_global = nn.Linear(global_c + nc, h0, bias=not bn)
        self.seg_head_bn = nn.BatchNorm1d(h0) if bn else None
        self.seg_head_mlp = SharedMLP(h0, cfg.seg_head_widths[1:], bn)
        self.seg_out = nn.Linear(self.seg_head_mlp.out_channels, 2)
        # 3. T-Net
        self.tnet_mlp = SharedMLP(3, cfg.tnet_widths, bn)
        self.tnet_head = FCHead(int(cfg.tnet_widths[-1]) + nc, cfg.tnet_fc, 3, bn)
        # 4. box PointNet and heads
        self.box_mlp = SharedMLP(3, cfg.box_widths, bn)
        feat_c = int(cfg.box_widths[-1])
        # the whole frustum around the stage-1 centre, with the hard mask as a 4th channel: what
        # lies around the object (the floor beyond it, a wall behind it) bounds its hidden extent
        self.ctx_mlp = SharedMLP(4, cfg.box_context_widths, bn) if cfg.box_context_widths else None
        ctx_c = self.ctx_mlp.out_channels if self.ctx_mlp is not None else 0
        self.box_head = FCHead(
            feat_c + nc + ctx_c, cfg.box_fc, box_head_channels(cfg.num_heading_bins, cfg.num_size_clusters), bn
        )
        # second box stage: every frustum point in the first box's unit-cube frame, hard mask as
        # a 4th channel; residual centre / log size / heading (zero output: the first box)
        self.box2_mlp = SharedMLP(4, cfg.box2_widths, bn) if cfg.box2_widths else None
        self.box2_head = None
        if self.box2_mlp is not None:
            self.box2_head = FCHead(self.box2_mlp.out_channels + feat_c + nc + 3, cfg.box2_fc, 7, bn)
            nn.init.zeros_(self.box2_head.out.weight)
            nn.init.zeros_(self.box2_head.out.bias)
        self.shape_mlp = SharedMLP(3, cfg.shape_widths, bn)
        shape_in = feat_c + nc + int(cfg.shape_widths[-1])
        # every frustum point in the shape box's unit-cube frame, hard mask as a 4th channel:
        # where the object is not (its feature columns come last in the shape head's input)
        self.shape_ctx_mlp = SharedMLP(4, cfg.shape_context_widths, bn) if cfg.shape_context_widths else None
        if self.shape_ctx_mlp is not None:
            shape_in += self.shape_ctx_mlp.out_channels
        self.shape_head = FCHead(shape_in, cfg.shape_fc, cfg.num_primitives * 10, bn)
        # per-class anchors of the raw primitive values (zeros until initialised from class
        # templates, see .shape_anchors); None without ``shape_anchors``
        self.shape_anchor = nn.Parameter(torch.zeros(nc, cfg.num_primitives * 10)) if cfg.shape_anchors else None
        self.cls_head = FCHead(global_c + feat_c, cfg.cls_fc, cfg.num_cls_outputs, bn, dropout=cfg.cls_dropout)
        self.register_buffer("cls_temperature", torch.tensor(1.0))
        self.register_buffer("mean_sizes", torch.tensor(cfg.mean_sizes, dtype=torch.float32))
        self._init_shape_head()

    def _init_shape_head(self) -> None:
        """Start primitives as identity-rotated, medium-sized cuboids spread over the box."""
        M = self.config.num_primitives
        out = self.shape_head.out
        with torch.no_grad():
            out.weight.mul_(0.1)
            b = torch.zeros(M, 10)
            g = torch.Generator().manual_seed(0)
            spread = (torch.rand(M, 3, generator=g) - 0.5) * 1.6
            b[:, 0:3] = math.log(0.35)  # 0.35 of the box size
            b[:, 7:10] = spread * 0.8
            b[:, 3] = 1.0  # quaternion w
            out.bias.copy_(b.reshape(-1))

    # ------------------------------------------------------------------ pieces
    def seg_features(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The class-independent part of the segmentation: the global feature (B,C) and the
        local points' first seg-head term (B,N,H). The class one-hot enters only after them
        (:meth:`segment`), so a second pass over the same points with another one-hot can
        reuse them (:meth:`forward`'s ``seg_cache``)."""
        cfg = self.config
        glob, local = self.seg_mlp.forward_max(pts[..., : cfg.in_channels], keep=cfg.seg_local_index)
        return glob, self.seg_head_local(local)

    def segment(
        self,
        pts: torch.Tensor,
        one_hot: torch.Tensor,
        features: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-point logits (B,N,2), the global segmentation feature (B,C) and the local
        seg-head term (B,N,H); ``features`` = :meth:`seg_features` of ``pts`` if known."""
        glob, h_local = self.seg_features(pts) if features is None else features
        h = h_local + self.seg_head_global(torch.cat([glob, one_hot], 1)).unsqueeze(1)
        if self.seg_head_bn is not None:
            shape = h.shape
            h = self.seg_head_bn(h.reshape(-1, shape[-1])).reshape(shape)
        h = self.seg_head_mlp(torch.relu(h))
        return self.seg_out(h), glob, h_local

    def gather_object_points(
        self, xyz: torch.Tensor, fg: torch.Tensor, random: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Gather ``num_object_points`` foreground points (with replacement).

        ``xyz`` (B,N,3), ``fg`` (B,N) bool. Returns the gathered points (B,NO,3), the
        masked-point mean (B,3) and the foreground count (B,) (rows without foreground
        use all points). ``random`` picks a random subset, otherwise evenly spread ones.
        """
        B, N, _ = xyz.shape
        NO = self.config.num_object_points
        count = fg.sum(1)
        fg = fg | (count == 0).unsqueeze(1)
        k = fg.sum(1)
        key = fg.to(xyz.dtype)
        if random:
            key = key + torch.rand(B, N, device=xyz.device, dtype=xyz.dtype)
        else:
            key = key - torch.arange(N, device=xyz.device, dtype=xyz.dtype) / (2 * N)
        order = key.argsort(dim=1, descending=True)
        ar = torch.arange(NO, device=xyz.device).unsqueeze(0)
        kk = k.unsqueeze(1)
        j = torch.where(kk >= NO, (ar * kk) // NO, ar % kk)
        idx = order.gather(1, j)
        obj = xyz.gather(1, idx.unsqueeze(-1).expand(-1, -1, 3))
        fgf = fg.to(xyz.dtype).unsqueeze(-1)
        mean = (xyz * fgf).sum(1) / k.clamp_min(1).to(xyz.dtype).unsqueeze(-1)
        return obj, mean, count

    def second_box_stage(
        self,
        xyz: torch.Tensor,
        fg: torch.Tensor,
        feat: torch.Tensor,
        one_hot: torch.Tensor,
        center: torch.Tensor,
        heading: torch.Tensor,
        size: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The second box stage (``box2_widths``): the box (``center`` (B,3), ``heading``
        (B,) about F's z, ``size`` (B,3), all frame F, metres / radians, taken as constants)
        refined from ``xyz`` (B,N,3, all frustum points) seen in its canonical frame divided by
        its size, the hard mask ``fg`` (B,N), the box feature and the class one-hot. Returns
        the refined centre, heading and size and the raw residuals (B,7): centre in box axes
        and box sizes, log size, heading (radians)."""
        c, s, h = center.detach(), size.detach(), heading.detach()
        q = to_unit_box(xyz, c, h, s).clamp(-4.0, 4.0)
        rfeat = self.box2_mlp.forward_max(torch.cat([q, fg.unsqueeze(-1).to(q.dtype)], -1))
        r = self.box2_head(torch.cat([rfeat, feat, one_hot, torch.log(s.clamp_min(0.02))], 1))
        r = r.to(c.dtype)
        dc = to_box_axes((r[:, 0:3] * s).unsqueeze(1), -h).squeeze(1)  # box axes -> frame F
        size2 = (s * torch.exp(r[:, 3:6].clamp(-1.0, 1.0))).clamp_min(0.02)
        return c + dc, h + r[:, 6], size2, r

    # ------------------------------------------------------------------ forward
    def forward(
        self,
        points: torch.Tensor,
        one_hot: torch.Tensor,
        random_gather: bool | None = None,
        fg_override: torch.Tensor | None = None,
        shape_box: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
        seg_cache: tuple[torch.Tensor, torch.Tensor] | None = None,
        with_shape: bool = True,
    ) -> dict[str, torch.Tensor]:
        """``points`` (B,N,>=3) frame F [+ rgb], ``one_hot`` (B,num_classes) (zeros allowed).

        ``fg_override`` (B,N) bool replaces the predicted hard mask (e.g. GT mask for
        teacher forcing); ``shape_box`` = (centre (B,3), heading (B,), size (B,3)) in F
        canonicalises the shape branch's input (default: the predicted box, detached).
        ``seg_cache`` = the ``seg_glob`` / ``seg_local`` outputs of an earlier forward over the
        same ``points`` (any one-hot): the segmentation PointNet is skipped, same result.
        ``with_shape=False`` skips the shape branch (no ``shape_raw``; every other output the
        same): inference passes whose primitives nobody reads.
        Returns a dict of tensors (see the module docstring); ``center``, ``box_heading``,
        ``box_size``, ``box_cluster`` are the decoded predicted box (size cluster = the
        given class, else the size head's argmax; after the second box stage when the network
        has one, which alone gives them gradients), ``center_head`` the box head's centre.
        """
        cfg = self.config
        if random_gather is None:
            random_gather = self.training
        seg_logits, seg_glob, seg_local = self.segment(points, one_hot, seg_cache)
        xyz = points[..., :3]
        fg = fg_override if fg_override is not None else (seg_logits[..., 1] > seg_logits[..., 0])
        obj, mask_mean, fg_count = self.gather_object_points(xyz, fg, random_gather)
        # T-Net
        local = obj - mask_mean.unsqueeze(1)
        tfeat = self.tnet_mlp.forward_max(local)
        center_delta = self.tnet_head(torch.cat([tfeat, one_hot], 1))
        stage1 = mask_mean + center_delta
        # box PointNet
        local = local - center_delta.unsqueeze(1)
        feat = self.box_mlp.forward_max(local)
        fo = torch.cat([feat, one_hot], 1)
        box_in = fo
        if self.ctx_mlp is not None:
            around = torch.cat([xyz - stage1.unsqueeze(1), fg.unsqueeze(-1).to(xyz.dtype)], -1)
            box_in = torch.cat([fo, self.ctx_mlp.forward_max(around)], 1)
        heads = split_box_head(self.box_head(box_in), cfg.num_heading_bins, cfg.num_size_clusters)
        center_head = stage1 + heads["center_res"]
        heading, given, cluster, size = self._decode_box(heads, one_hot)
        center = center_head
        box2_res = None
        if self.box2_mlp is not None:
            center, heading, size, box2_res = self.second_box_stage(xyz, fg, feat, one_hot, center_head, heading, size)
        cls_logits = self.cls_head(torch.cat([seg_glob, feat], 1))
        shape_raw = None
        if with_shape:
            shape_raw = self._shape_raw(obj, xyz, fg, fo, one_hot, given, cls_logits,
                                        (center, heading, size) if shape_box is None else shape_box)
        out: dict[str, torch.Tensor] = {
            "seg_logits": seg_logits,
            "seg_glob": seg_glob,
            "seg_local": seg_local,
            "fg_count": fg_count,
            "mask_mean": mask_mean,
            "stage1_center": stage1,
            "center_head": center_head,
            "center": center,
            "box_heading": heading,
            "box_size": size,
            "box_cluster": cluster,
            "cls_logits": cls_logits,
        }
        if shape_raw is not None:
            out["shape_raw"] = shape_raw.view(-1, cfg.num_primitives, 10)
        if box2_res is not None:
            out["box2_res"] = box2_res
        out.update(heads)
        return out

    def _decode_box(
        self, heads: dict[str, torch.Tensor], one_hot: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The box head's decoded box, without gradients: heading (B,) rad about F's z, whether
        a class is given (B,) bool, size cluster (B,) (the given class, else the size head's
        argmax) and size (B,3) m (at least 2 cm)."""
        cfg = self.config
        with torch.no_grad():
            hcls = heads["heading_scores"].argmax(1)
            heading = decode_heading(hcls, gather_bin(heads["heading_res_norm"], hcls), cfg.num_heading_bins)
            given = one_hot.sum(1) > 0
            cluster = torch.where(given, one_hot.argmax(1), heads["size_scores"].argmax(1))
            size = decode_size(cluster, gather_bin(heads["size_res_norm"], cluster), self.mean_sizes).clamp_min(0.02)
        return heading, given, cluster, size

    def _shape_raw(
        self,
        obj: torch.Tensor,
        xyz: torch.Tensor,
        fg: torch.Tensor,
        fo: torch.Tensor,
        one_hot: torch.Tensor,
        given: torch.Tensor,
        cls_logits: torch.Tensor,
        shape_box: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    ) -> torch.Tensor:
        """The shape head's raw output (B, M*10): the object points ``obj`` (B,NO,3) and all
        frustum points ``xyz`` (B,N,3, hard mask ``fg``) in the unit-cube frame of
        ``shape_box`` (centre, heading, size; frame F, taken as constants), with the box
        feature + one-hot ``fo``, plus the anchor row of the given class (``given``), else of
        the class head's best class."""
        sc, sh, ss = (t.detach() for t in shape_box)
        shape_in = torch.cat([fo, self.shape_mlp.forward_max(to_unit_box(obj, sc, sh, ss))], 1)
        if self.shape_ctx_mlp is not None:
            qa = to_unit_box(xyz, sc, sh, ss).clamp(-4.0, 4.0)
            qa = torch.cat([qa, fg.unsqueeze(-1).to(qa.dtype)], -1)
            shape_in = torch.cat([shape_in, self.shape_ctx_mlp.forward_max(qa)], 1)
        shape_raw = self.shape_head(shape_in)
        if self.shape_anchor is not None:
            anchor_cls = torch.where(given, one_hot.argmax(1), cls_logits[:, : self.config.num_classes].argmax(1))
            shape_raw = shape_raw + self.shape_anchor[anchor_cls]
        return shape_raw

    @torch.no_grad()
    def fuse_batchnorm(self) -> FrustumShapeNet:
        """Fold every BatchNorm into its linear layer (inference only: call in eval mode,
        after loading weights; the module can no longer be trained or saved as weights)."""
        from .pointnet import PointLinear, fuse_linear_bn

        if self.training:
            raise RuntimeError("fuse_batchnorm() is for eval mode only")
        for m in self.modules():
            if isinstance(m, PointLinear):
                m.fuse_batchnorm()
        if self.seg_head_bn is not None:
            bn = self.seg_head_bn
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            self.seg_head_local.weight.mul_(scale.unsqueeze(1))
            self.seg_head_global = fuse_linear_bn(self.seg_head_global, bn)
            self.seg_head_bn = None
        self._fused = True
        return self

    def part_names(self, names: list[str] | tuple[str, ...]) -> set[str]:
        """The child modules / parameters named by ``names`` (group names of
        :attr:`MODULE_GROUPS` or exact child names); an unknown or absent name is an error."""
        out: set[str] = set()
        for n in names:
            kids = self.MODULE_GROUPS.get(str(n), (str(n),))
            for k in kids:
                if k not in self._modules and k not in self._parameters:
                    raise ValueError(f"no network part named {k!r} (from {n!r})")
                if getattr(self, k) is not None:
                    out.add(k)
        return out

    def num_parameters(self) -> int:
        """Number of parameters (all, trainable or not)."""
        return sum(p.numel() for p in self.parameters())
