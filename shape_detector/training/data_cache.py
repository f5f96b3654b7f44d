"""Training data on disk: generated data sets and frustum caches keyed by content.

A frustum cache's name is a hash of what decides its content: the source data set's
identity (for a generated set its seed, frame count and generator version, read from its
``index.json``; for anything else the sha256 of its files), the extraction settings
(:class:`~.frustum_dataset.FrustumDatasetConfig`), the frame limit and
:data:`FRUSTUM_CACHE_VERSION`. Paths and modification times play no part: moving or
regenerating a data set with the same seed reuses the cache, changing a setting does not.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..digests import sha256_file, sha256_json
from .provenance import dataset_identity

#: bump when frustum extraction changes what it writes for the same inputs
FRUSTUM_CACHE_VERSION = 1


def data_identity(path: str | Path) -> dict[str, Any]:
    """What identifies a data set's content (no paths): see the module docstring."""
    p = Path(path)
    ident = dataset_identity(p)
    ident.pop("path", None)
    if "seed" in ident or "sha256" in ident:
        return ident
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else []
    if not files:
        raise FileNotFoundError(f"no data in {p}")
    return {"files_sha256": sha256_json({str(f.relative_to(p)): sha256_file(f) for f in files})}


def ensure_dataset(root: Path, name: str, spec: dict[str, Any], workers: int = 2,
                   say: Callable[[str], None] = print) -> Path:
    """``root/name``: a generated data set with ``spec``'s ``seed`` and ``frames`` (written
    now when missing; refused when an existing one has another seed or frame count)."""
    from ..synth.dataset import write_shards
    from ..synth.generate import SynthConfig

    out = Path(root) / name
    idx = out / "index.json"
    if idx.is_file():
        index = json.loads(idx.read_text())
        if index.get("seed") != spec["seed"] or index.get("num_frames") != spec["frames"]:
            raise ValueError(f"{out}: seed {index.get('seed')}, {index.get('num_frames')} frames; the recipe wants "
                             f"seed {spec['seed']}, {spec['frames']} frames (use another --data-root)")
        return out
    say(f"data set {name}: generating {spec['frames']} frames with seed {spec['seed']} -> {out}")
    write_shards(out, int(spec["frames"]), seed=int(spec["seed"]),
                 frames_per_shard=int(spec.get("frames_per_shard", 150)), workers=workers,
                 config=SynthConfig(**spec.get("synth", {})), rgb_format=spec.get("rgb_format", "jpg"), quiet=True)
    return out


def frustum_config(cfg_data: dict[str, Any], num_points: int, tag: str):
    """The extraction settings of a frustum set: ``cfg_data`` overrides, the network's point
    count; a validation set (``tag == "val"``) has one copy per object and its own seed."""
    from . import frustum_dataset as fds

    data_cfg = fds.FrustumDatasetConfig.from_dict(cfg_data)
    data_cfg.num_points = int(num_points)
    if tag == "val":
        data_cfg.augment_copies = 1
    data_cfg.rng_seed = int(data_cfg.rng_seed) + (0 if tag == "train" else 1000)
    return data_cfg


def frustum_key(source: str | Path, data_cfg, max_frames: int | None) -> str:
    """The content key of the frustums of ``source`` extracted with ``data_cfg``."""
    return sha256_json({"data": data_identity(source), "extract": data_cfg.to_dict(), "max_frames": max_frames,
                        "version": FRUSTUM_CACHE_VERSION})[:16]


def get_frustums(source: str | Path, cfg_data: dict[str, Any], num_points: int, cache_dir: Path, tag: str,
                 max_frames: int | None = None, say: Callable[[str], None] = print) -> dict:
    """Frustum dataset of ``source``: a frustum ``.npz`` as is, or built from generated
    shards and cached in ``cache_dir`` under its content key."""
    from ..synth.dataset import iter_frames
    from . import frustum_dataset as fds

    source = Path(source)
    if source.is_file() and source.suffix == ".npz":
        return fds.load(source)
    data_cfg = frustum_config(cfg_data, num_points, tag)
    cache = Path(cache_dir) / f"frustums_{tag}_{frustum_key(source, data_cfg, max_frames)}.npz"
    if cache.is_file():
        say(f"{tag} frustums: cached {cache}")
        return fds.load(cache)
    t0 = time.time()
    frames = iter_frames(source)
    if max_frames:
        frames = itertools.islice(frames, int(max_frames))
    say(f"{tag} frustums: building from {source} ...")
    ds = fds.build_frustum_dataset(frames, config=data_cfg, num_points=data_cfg.num_points,
                                   augment_copies=data_cfg.augment_copies, rng_seed=data_cfg.rng_seed,
                                   negatives_per_frame=data_cfg.negatives_per_frame, progress=False)
    fds.save(ds, cache)
    say(f"{tag} frustums: {fds.summary(ds)} in {time.time() - t0:.0f}s -> {cache}")
    return ds
