"""Starting a run from trained weights: copying them (growing new branches as no-ops),
class-template shape anchors, and freezing every part a phase does not train."""

from __future__ import annotations

import numpy as np
import torch

from ..model.network import FrustumShapeNet

#: model-config keys of the primitive mapping: may differ only when the shape head restarts
_SHAPE_MAPPING_KEYS = ("primitive_min_size_frac",)
#: model-config keys that set how many points are sampled, not any parameter's shape: a run
#: may fine-tune at other counts than its init was trained with
_SAMPLING_KEYS = ("num_points", "num_object_points")
#: config keys of each branch that may be added to an init without it -> its child modules
_GROWABLE = {
    "box_context_widths": ("ctx_mlp",),
    "box2_widths": ("box2_mlp", "box2_head"),
    "shape_context_widths": ("shape_ctx_mlp",),
}


def _grown(model: FrustumShapeNet, init_model: FrustumShapeNet) -> set[str]:
    """Children ``model`` has and ``init_model`` lacks (they start fresh, as no-ops)."""
    out = set()
    for kids in _GROWABLE.values():
        if getattr(model, kids[0]) is not None and getattr(init_model, kids[0]) is None:
            out.update(kids)
    if model.shape_anchor is not None and init_model.shape_anchor is None:
        out.add("shape_anchor")
    return out


def _check_configs(model: FrustumShapeNet, init_model: FrustumShapeNet, fresh: set[str]) -> None:
    a, b = model.config.to_dict(), init_model.config.to_dict()
    drop: list[str] = list(_SAMPLING_KEYS)
    if "shape_anchor" in fresh or "shape_head" in fresh:
        drop += list(_SHAPE_MAPPING_KEYS)
    if "shape_anchor" in fresh:
        drop.append("shape_anchors")
    for key, kids in _GROWABLE.items():
        if kids[0] in fresh and getattr(init_model, kids[0]) is None:
            drop += [key] + (["box2_fc"] if key == "box2_widths" else [])
    for k in drop:
        a.pop(k, None), b.pop(k, None)
    if a != b:
        diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        raise ValueError(f"--init: its model config differs from the training config's ({diff})")


def load_init(model: FrustumShapeNet, init_model: FrustumShapeNet, reinit: list[str] | None) -> bool:
    """Copy ``init_model``'s parameters into ``model`` except the ``reinit`` parts, which keep
    their fresh initialisation. The model configs must be equal, except the point counts
    (:data:`_SAMPLING_KEYS`), the primitive mapping
    when the shape head restarts or gets its first class anchors, and the box context branch,
    second box stage or shape context branch when ``model`` adds them (each starts as a no-op).
    Returns whether the class anchors came from ``init_model``."""
    restart = model.part_names(reinit) if reinit else set()
    if reinit and not restart:
        raise ValueError(f"reinit={list(reinit)}: no parameter matches")
    grown = _grown(model, init_model)
    fresh = restart | grown
    _check_configs(model, init_model, fresh)

    def is_fresh(key: str) -> bool:
        return key.split(".")[0] in fresh

    state = {k: v for k, v in init_model.state_dict().items() if not is_fresh(k)}
    # a new context feature enters its head's first layer (its first weight matrix) as the last
    # input columns, with zero weights, so the network starts out computing what init_model did
    for head, new in (("box_head.", "ctx_mlp" in grown), ("shape_head.", "shape_ctx_mlp" in grown)):
        if new and head[:-1] not in restart:
            key = next(k for k, v in state.items() if k.startswith(head) and v.dim() == 2)
            w = torch.zeros_like(model.state_dict()[key])
            w[:, : state[key].shape[1]] = state[key]
            state[key] = w
    missing, unexpected = model.load_state_dict(state, strict=False)
    if unexpected or not all(is_fresh(k) for k in missing):
        raise ValueError(f"--init: parameters do not match (missing {missing}, unexpected {unexpected})")
    return "shape_anchor" in state


@torch.no_grad()
def init_shape_anchors(model: FrustumShapeNet, ds: dict[str, np.ndarray], seed: int = 0) -> np.ndarray:
    """Set ``model.shape_anchor`` to the class templates of ``ds``'s GT parts
    (:func:`shape_detector.model.shape_anchors.class_templates`) and zero the shape head's
    output layer, so every object starts at its class template. Returns the per-class
    bool of classes found (the others keep zero anchors)."""
    from ..model.shape_anchors import class_templates, templates_to_raw

    cfg = model.config
    lo, hi, found = class_templates(
        ds["parts_center"], ds["parts_size"], ds["parts_rotation"],
        np.where(ds["has_shape"] & ~ds["is_negative"], ds["parts_count"], 0), ds["size"], ds["class_id"],
        cfg.num_classes, cfg.num_primitives, seed=seed,
    )
    raw = templates_to_raw(lo, hi, **cfg.primitive_kwargs()).reshape(cfg.num_classes, -1)
    raw[~found] = 0.0
    model.shape_anchor.copy_(torch.as_tensor(raw, dtype=model.shape_anchor.dtype))
    model.shape_head.out.weight.zero_()
    model.shape_head.out.bias.zero_()
    return found


def class_path_frozen(trainable: list[str] | None) -> bool:
    """Whether a run training only the ``trainable`` parts leaves the class logits as they
    were (every part lies off the class path)."""
    if not trainable:
        return False
    kids = {k for n in trainable for k in FrustumShapeNet.MODULE_GROUPS.get(str(n), (str(n),))}
    return kids <= FrustumShapeNet.OFF_CLASS_PATH


def freeze(model: FrustumShapeNet, trainable: list[str] | None) -> list[torch.nn.Module]:
    """Freeze every parameter outside the ``trainable`` parts; returns the frozen leaf
    modules (to keep in eval mode: frozen BatchNorm keeps its statistics). None or empty:
    nothing frozen."""
    if not trainable:
        return []
    parts = model.part_names(trainable)
    for name, prm in model.named_parameters():
        prm.requires_grad_(name.split(".")[0] in parts)
    if not any(p.requires_grad for p in model.parameters()):
        raise ValueError(f"trainable={trainable}: no parameter matches")
    return [m for name, m in model.named_modules() if name and name.split(".")[0] not in parts
            and not any(True for _ in m.children())]
