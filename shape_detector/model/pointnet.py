"""PointNet building blocks, channels-last.

Point features are ``(B, N, C)`` tensors; a shared (per-point) MLP is a stack of
``nn.Linear`` layers applied to the last axis (on CPU a plain GEMM over ``B*N`` rows is
faster than ``Conv1d`` with kernel 1), each followed by optional BatchNorm (statistics
over all ``B*N`` points, so a single frustum at inference is fine in eval mode) and ReLU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class PointLinear(nn.Module):
    """One shared per-point layer: Linear -> (BatchNorm) -> ReLU on ``(..., C)``."""

    def __init__(self, c_in: int, c_out: int, batchnorm: bool = True, relu: bool = True) -> None:
        super().__init__()
        self.linear = nn.Linear(c_in, c_out, bias=not batchnorm)
        self.bn = nn.BatchNorm1d(c_out) if batchnorm else None
        self.relu = relu

    @torch.no_grad()
    def fuse_batchnorm(self) -> None:
        """Fold the (eval-mode) BatchNorm into the linear layer, for inference only."""
        if self.bn is None:
            return
        self.linear = fuse_linear_bn(self.linear, self.bn)
        self.bn = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., c_in)`` -> ``(..., c_out)``."""
        y = self.linear(x)
        if self.bn is not None:
            shape = y.shape
            y = self.bn(y.reshape(-1, shape[-1])).reshape(shape)
        if not self.relu:
            return y
        return torch.relu(y) if self.training else torch.relu_(y)  # in place: one pass less at inference


class SharedMLP(nn.Module):
    """A stack of :class:`PointLinear` layers; ``forward`` may return every layer's output."""

    def __init__(self, c_in: int, widths: Sequence[int], batchnorm: bool = True) -> None:
        super().__init__()
        layers = []
        c = c_in
        for w in widths:
            layers.append(PointLinear(c, int(w), batchnorm))
            c = int(w)
        self.layers = nn.ModuleList(layers)
        self.out_channels = c

    def forward(self, x: torch.Tensor, return_all: bool = False):
        """``(B, N, C_in)`` -> the last layer's ``(B, N, C_out)``, or with ``return_all`` a list of every layer's output."""
        outs = []
        for layer in self.layers:
            x = layer(x)
            outs.append(x)
        return outs if return_all else x

    def forward_max(self, x: torch.Tensor, keep: int | None = None):
        """``forward(x)`` max-pooled over the point axis: (B, N, C_in) -> (B, C_out); with
        ``keep`` (index of a layer before the last) also that layer's per-point output.

        With the last layer's BatchNorm folded (inference), its bias and ReLU commute with
        the max (``max_n relu(z_n W + b) = relu(max_n(z_n W) + b)``), so they run on the
        pooled (B, C) feature instead of the widest (B, N, C) tensor; same result.
        """
        *body, last = self.layers
        kept = None
        for i, layer in enumerate(body):
            x = layer(x)
            if i == keep:
                kept = x
        if keep is not None and kept is None:
            raise ValueError(f"keep={keep} must index a layer before the last of {len(self.layers)}")
        if last.bn is not None or self.training:
            y = last(x).amax(dim=1)
        else:
            y = torch.matmul(x, last.linear.weight.t()).amax(dim=1)
            if last.linear.bias is not None:
                y = y + last.linear.bias
            if last.relu:
                y = torch.relu(y)
        return y if keep is None else (y, kept)


class FCHead(nn.Module):
    """Fully connected layers (Linear -> BN -> ReLU [-> dropout]) and a linear output."""

    def __init__(
        self,
        c_in: int,
        widths: Sequence[int],
        c_out: int,
        batchnorm: bool = True,
        dropout: float = 0.0,
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = c_in
        for w in widths:
            layers.append(PointLinear(c, int(w), batchnorm))
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
            c = int(w)
        self.body = nn.Sequential(*layers)
        self.out = nn.Linear(c, c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, c_in)`` -> ``(B, c_out)``."""
        return self.out(self.body(x))


@torch.no_grad()
def fuse_linear_bn(linear: nn.Linear, bn: nn.BatchNorm1d) -> nn.Linear:
    """A Linear equal to ``bn(linear(x))`` with the BatchNorm's running statistics."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    out = nn.Linear(linear.in_features, linear.out_features, bias=True).to(linear.weight)
    out.weight.copy_(linear.weight * scale.unsqueeze(1))
    b = linear.bias if linear.bias is not None else torch.zeros_like(bn.running_mean)
    out.bias.copy_((b - bn.running_mean) * scale + bn.bias)
    return out


def masked_max(x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Max over the point axis of ``x`` (B, N, C); ``mask`` (B, N) bool limits the points."""
    if mask is None:
        return x.amax(dim=1)  # amax: ~10x faster than max(dim).values, which also finds indices
    neg = torch.finfo(x.dtype).min
    return x.masked_fill(~mask.unsqueeze(-1), neg).amax(dim=1)


def set_bn_momentum(module: nn.Module, momentum: float) -> None:
    """Set the momentum of every BatchNorm layer (torch convention: weight of the new batch)."""
    for m in module.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.momentum = float(momentum)
