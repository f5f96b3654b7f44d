"""TorchScript graphs of the inference forward: fewer dispatches, and no GIL while they run.

The eager forward of :class:`~shape_detector.model.network.FrustumShapeNet` is a few
thousand small torch ops, each dispatched from Python under the GIL. Beside another
Python thread (the node's pipeline runs the proposer in one thread while the network runs
in the other) every op waits for that thread to let go of the GIL, and beside a busy
pure-Python loop a forward slows down by orders of magnitude. A traced and frozen graph runs
in TorchScript's interpreter, which releases the GIL for the whole call (only the Python
around the call still waits), and skips the per-op Python overhead (under bfloat16 the
frozen graph also casts the weights once instead of at every call).
``shape-detector bench network`` prints the times (``beside_python``).

Outputs are bit-identical to the eager forward (the graphs are traced from it, per
variant: with or without a segmentation-feature cache, fp32 or bfloat16 autocast, the
inputs' dtypes and point count); the batch size stays dynamic. ``torch.jit`` is
deprecated in favour of ``torch.compile``, which needs a C++ toolchain at run time and
compiles for tens of seconds; where tracing is unavailable or fails, :class:`TracedModule`
falls back to the eager module (with one warning).
"""

from __future__ import annotations

import threading
import warnings

import torch
from torch import nn

from .primitives import primitive_params

#: what :func:`inference_outputs` returns, in this order (the graphs return tuples)
OUTPUT_KEYS = (
    "probs",
    "seg_prob",
    "center",
    "heading",
    "heading_conf",
    "size",
    "cluster",
    "fg_score",
    "prim_center",
    "prim_size",
    "prim_rotation",
    "seg_glob",
    "seg_local",
)


def inference_outputs(
    model: nn.Module,
    points: torch.Tensor,
    one_hot: torch.Tensor,
    seg_cache: tuple[torch.Tensor, torch.Tensor] | None = None,
    with_shape: bool = True,
) -> tuple[torch.Tensor, ...]:
    """The network's forward and its decoding for inference, :data:`OUTPUT_KEYS` in order
    (frame F): temperature-calibrated class probabilities (background last), per-point
    foreground probability, box centre / heading / size / size cluster, the heading bin's
    confidence, the mean foreground probability of the foreground points, the primitives
    (canonical frame), all float32, and the class-independent segmentation features (in the
    forward's dtype). The decoding runs outside any autocast region, in the dtype the forward
    left. ``with_shape=False`` skips the shape branch: the primitives are then zeros."""
    out = model(points, one_hot, random_gather=False, seg_cache=seg_cache, with_shape=with_shape)
    with torch.autocast(points.device.type, enabled=False):
        probs = torch.softmax(out["cls_logits"] / model.cls_temperature.clamp_min(1e-3), dim=1)
        seg_prob = torch.softmax(out["seg_logits"], dim=-1)[..., 1]
        if with_shape:
            prims = primitive_params(out["shape_raw"], out["box_size"], **model.config.primitive_kwargs())
        else:
            z = out["box_size"].new_zeros(out["box_size"].shape[0], model.config.num_primitives, 3)
            prims = {"center": z, "size": z, "rotation": z.unsqueeze(-1).expand(-1, -1, -1, 3)}
        heading_conf = torch.softmax(out["heading_scores"].float(), dim=1).amax(1)
        fg = seg_prob > 0.5
        fg_score = (seg_prob * fg).sum(1) / fg.sum(1).clamp_min(1)
    decoded = (
        probs, seg_prob, out["center"], out["box_heading"], heading_conf, out["box_size"], out["box_cluster"],
        fg_score, prims["center"], prims["size"], prims["rotation"],
    )
    return (*(t.float() for t in decoded), out["seg_glob"], out["seg_local"])


class _Plain(nn.Module):
    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, points: torch.Tensor, one_hot: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return inference_outputs(self.model, points, one_hot)


class _Cached(nn.Module):
    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(
        self, points: torch.Tensor, one_hot: torch.Tensor, seg_glob: torch.Tensor, seg_local: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        return inference_outputs(self.model, points, one_hot, (seg_glob, seg_local))


class TracedModule:
    """``module(*args)`` (tensors in, a tuple of tensors out) through frozen TorchScript graphs,
    one per variant: bfloat16 autocast or not, and each argument's dtype and shape after the
    batch axis (the batch size stays dynamic). A variant is traced on first use (thread-safe);
    ``enabled=False``, or a tracing failure (one warning), runs the eager ``module``.
    ``module`` must be in eval mode and must not change afterwards.
    """

    def __init__(self, module: nn.Module, enabled: bool = True) -> None:
        self.module = module.eval()
        self.enabled = bool(enabled) and hasattr(torch, "jit")
        self._graphs: dict[tuple, torch.jit.ScriptModule] = {}
        self._lock = threading.Lock()

    @property
    def traced(self) -> int:
        """How many graph variants are traced so far."""
        return len(self._graphs)

    def _eager(self, args: tuple[torch.Tensor, ...], bf16: bool) -> tuple[torch.Tensor, ...]:
        with torch.autocast(args[0].device.type, dtype=torch.bfloat16, enabled=bf16):
            return self.module(*args)

    def _graph(self, key: tuple, args: tuple[torch.Tensor, ...], bf16: bool):
        graph = self._graphs.get(key)
        if graph is not None or not self.enabled:
            return graph
        with self._lock:
            graph = self._graphs.get(key)
            if graph is None and self.enabled:
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # TracerWarning / torch.jit's deprecation notice
                        with torch.autocast(args[0].device.type, dtype=torch.bfloat16, enabled=bf16):
                            graph = torch.jit.trace(self.module, args, check_trace=False)
                        # frozen outside autocast: folding constants under it rounds them differently
                        graph = torch.jit.freeze(graph)
                    self._graphs[key] = graph
                except Exception as e:  # noqa: BLE001 - any tracing failure: run eagerly
                    self._eager(args, bf16)  # raises if the inputs themselves are wrong
                    self.enabled = False
                    warnings.warn(f"TorchScript tracing failed ({type(e).__name__}: {e}); running eagerly", stacklevel=3)
                    graph = None
        return graph

    def __call__(self, *args: torch.Tensor, bf16: bool = False) -> tuple[torch.Tensor, ...]:
        """``module(*args)`` through the graph of this variant (traced now if new), or eagerly."""
        key = (bool(bf16), tuple((a.dtype, tuple(a.shape[1:])) for a in args))
        graph = self._graph(key, args, bool(bf16))
        return graph(*args) if graph is not None else self._eager(args, bool(bf16))


class TracedForward:
    """``forward(points, one_hot, seg_cache, bf16)`` -> :func:`inference_outputs` as a dict,
    through :class:`TracedModule` graphs of the first pass and of the feature-reusing second
    pass. ``model``: an eval-mode network; ``enabled=False``: eager."""

    def __init__(self, model: nn.Module, enabled: bool = True) -> None:
        self._plain = TracedModule(_Plain(model), enabled)
        self._cached = TracedModule(_Cached(model), enabled)

    @property
    def enabled(self) -> bool:
        """False once tracing is off (asked for, or failed for either pass)."""
        return self._plain.enabled and self._cached.enabled

    @property
    def traced(self) -> int:
        """How many graph variants are traced so far."""
        return self._plain.traced + self._cached.traced

    def __call__(
        self,
        points: torch.Tensor,
        one_hot: torch.Tensor,
        seg_cache: tuple[torch.Tensor, torch.Tensor] | None = None,
        bf16: bool = False,
    ) -> dict[str, torch.Tensor]:
        """:func:`inference_outputs` as a dict, for (B,N,C) ``points`` and (B,K) ``one_hot``;
        ``seg_cache`` = (seg_glob (B,G), seg_local (B,N,H)) of an earlier pass over the same points."""
        if seg_cache is None:
            outs = self._plain(points, one_hot, bf16=bf16)
        else:
            outs = self._cached(points, one_hot, *seg_cache, bf16=bf16)
        return dict(zip(OUTPUT_KEYS, outs))
