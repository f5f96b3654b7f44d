"""The learned 2D proposer's network (PyTorch, for training and export; inference runs the
exported ONNX graph, :mod:`shape_detector.proposals.learned`).

A small encoder-decoder: four stride-2 stages (24-48-64-96 channels, dilated convolutions
in the deeper two for context), upsampled back to a quarter of the input with skip
connections; two heads at that resolution: the centre heatmap (1 logit) and the box
regression (offset x, offset y, log width, log height in output cells), CenterNet's
decomposition (Zhou et al., "Objects as Points", 2019).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

#: heatmap bias at start: sigmoid(-2.19) = 0.1, CenterNet's prior for rare centres
HEATMAP_PRIOR_BIAS = -2.19


def _cbr(i: int, o: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(i, o, 3, stride, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(o), nn.ReLU(inplace=True))


class Proposer2DNet(nn.Module):
    """(B, 5, H, W) input -> ``(heatmap (B,1,H/4,W/4), reg (B,4,H/4,W/4))``."""

    def __init__(self, in_channels: int = 5) -> None:
        super().__init__()
        self.stem = nn.Sequential(_cbr(in_channels, 24, 2), _cbr(24, 32))
        self.down1 = nn.Sequential(_cbr(32, 48, 2), _cbr(48, 48))
        self.down2 = nn.Sequential(_cbr(48, 64, 2), _cbr(64, 64), _cbr(64, 64, dilation=2))
        self.down3 = nn.Sequential(_cbr(64, 96, 2), _cbr(96, 96), _cbr(96, 96, dilation=2))
        self.lat2 = nn.Conv2d(64, 96, 1)
        self.up2 = _cbr(96, 64)
        self.lat1 = nn.Conv2d(48, 64, 1)
        self.up1 = nn.Sequential(_cbr(64, 64), _cbr(64, 64))
        self.heatmap = nn.Sequential(_cbr(64, 32), nn.Conv2d(32, 1, 1))
        self.reg = nn.Sequential(_cbr(64, 32), nn.Conv2d(32, 4, 1))
        nn.init.constant_(self.heatmap[-1].bias, HEATMAP_PRIOR_BIAS)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heatmap logits and box regression on the quarter-resolution grid."""
        x1 = self.down1(self.stem(x))
        x2 = self.down2(x1)
        x3 = self.down3(x2)
        y2 = self.up2(self.lat2(x2) + F.interpolate(x3, size=x2.shape[-2:], mode="nearest"))
        y1 = self.up1(self.lat1(x1) + F.interpolate(y2, size=x1.shape[-2:], mode="nearest"))
        return self.heatmap(y1), self.reg(y1)
