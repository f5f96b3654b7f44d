"""A Frustum PointNets v1 forward (Qi et al., CVPR 2018) as a speed reference, in PyTorch.

Only for ``shape-detector bench``: it has the published v1 layer widths (instance
segmentation 64-64-64-128-1024 with a 512-256-128-128 head, T-Net 128-128-256 + 256-128,
box estimation 128-128-256-512 + 512-256) with BatchNorm after every hidden layer, 1x1
convolutions over the points as in the original, and random weights: the arithmetic a peer
method spends per frustum, not a detector. Inputs: ``points`` (B, N, 4) and a class one-hot
(B, C); ``num_object_points`` masked points go to the box stages (with replacement).
"""

from __future__ import annotations

from typing import Any

#: heading bins and size clusters of the v1 box head (KITTI settings)
NUM_HEADING_BINS = 12
NUM_SIZE_CLUSTERS = 8


def build_fpointnet_v1(num_classes: int = 10, num_object_points: int = 512) -> Any:
    """An eval-mode v1 network (random weights); ``net(points, one_hot)`` -> the box head's
    (B, 3 + 2 NH + 4 NS) output."""
    import torch
    from torch import nn

    def convs(c_in: int, widths: tuple[int, ...]) -> nn.Sequential:
        layers: list[nn.Module] = []
        for w in widths:
            layers += [nn.Conv1d(c_in, w, 1), nn.BatchNorm1d(w), nn.ReLU()]
            c_in = w
        return nn.Sequential(*layers)

    def fcs(c_in: int, widths: tuple[int, ...], c_out: int) -> nn.Sequential:
        layers: list[nn.Module] = []
        for w in widths:
            layers += [nn.Linear(c_in, w), nn.BatchNorm1d(w), nn.ReLU()]
            c_in = w
        return nn.Sequential(*layers, nn.Linear(c_in, c_out))

    class FPointNetV1(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.seg_local = convs(4, (64, 64))
            self.seg_global = convs(64, (64, 128, 1024))
            self.seg_head = nn.Sequential(convs(64 + 1024 + num_classes, (512, 256, 128, 128)), nn.Conv1d(128, 2, 1))
            self.tnet = convs(3, (128, 128, 256))
            self.tnet_fc = fcs(256 + num_classes, (256, 128), 3)
            self.box = convs(3, (128, 128, 256, 512))
            self.box_fc = fcs(512 + num_classes, (512, 256), 3 + 2 * NUM_HEADING_BINS + 4 * NUM_SIZE_CLUSTERS)

        def forward(self, points: torch.Tensor, one_hot: torch.Tensor) -> torch.Tensor:
            x = points.transpose(1, 2)  # (B, 4, N)
            n = x.shape[2]
            local = self.seg_local(x)
            glob = self.seg_global(local).amax(dim=2, keepdim=True)
            cond = torch.cat([glob, one_hot.unsqueeze(2)], 1).expand(-1, -1, n)
            logits = self.seg_head(torch.cat([local, cond], 1))
            fg = logits[:, 1] > logits[:, 0]
            # masked points, evenly picked with replacement (all points where none is foreground)
            key = fg.float() + torch.rand_like(fg.float()) * 0.5
            idx = key.argsort(dim=1, descending=True)[:, :num_object_points]
            xyz = points[..., :3].gather(1, idx.unsqueeze(-1).expand(-1, -1, 3))
            xyz = xyz - xyz.mean(1, keepdim=True)
            t = self.tnet_fc(torch.cat([self.tnet(xyz.transpose(1, 2)).amax(2), one_hot], 1))
            feat = self.box((xyz - t.unsqueeze(1)).transpose(1, 2)).amax(2)
            return self.box_fc(torch.cat([feat, one_hot], 1))

    return FPointNetV1().eval()


def time_fpointnet_v1(batch: int = 10, num_points: int = 1024, repeats: int = 10, threads: int = 1) -> dict[str, float]:
    """Median wall-clock and process-CPU ms (``ms_p50``, ``cpu_ms_p50``) of one v1 forward of
    ``batch`` frustums of ``num_points`` points in PyTorch (inference mode, ``threads``
    intra-op threads, restored afterwards)."""
    import time

    import numpy as np
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(int(threads))
    try:
        torch.manual_seed(0)
        net = build_fpointnet_v1()
        pts = torch.randn(batch, num_points, 4)
        one_hot = torch.zeros(batch, 10)
        one_hot[:, 0] = 1.0
        wall, cpu = [], []
        with torch.inference_mode():
            for i in range(repeats + 2):
                t0, c0 = time.perf_counter(), time.process_time()
                net(pts, one_hot)
                if i >= 2:
                    wall.append(1e3 * (time.perf_counter() - t0))
                    cpu.append(1e3 * (time.process_time() - c0))
    finally:
        torch.set_num_threads(before)
    return {"ms_p50": float(np.median(wall)), "cpu_ms_p50": float(np.median(cpu)), "threads": int(threads)}
