"""Provenance of a weights file: what made it, so that it can be made again.

Every weights file written by training carries a ``provenance`` dict (plain types)::

    git_commit        commit of the code that trained it ("unknown" outside a git checkout;
                      "+dirty" appended when tracked files had changes)
    recipe            recipe file name;  recipe_sha256: sha256 of its resolved content
    phase             the recipe phase that wrote it
    data              [{"path", "seed", "frames", "generator_version"}] of each data set used
    parents           [{"phase", "sha256"}] of the weights it was initialised from
    metrics           validation metrics at save
    torch_version, created_utc (ISO 8601), world_size (processes that trained it)
    reconstructed     true when the block was written after the fact from the history
    notes             free text (what is reconstructed and from where)
"""

from __future__ import annotations

import datetime as _dt
import json
import subprocess
from pathlib import Path
from typing import Any

import torch

from ..digests import sha256_file, sha256_json
from ..model.io import plain

_PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def git_commit(root: str | Path = _PACKAGE_ROOT) -> str:
    """The checkout's HEAD commit (``+dirty`` when tracked files changed), else ``"unknown"``."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def dataset_identity(path: str | Path) -> dict[str, Any]:
    """Seed, frame count and generator version of a generated data set (shard directory with
    ``index.json``); for anything else its file name and content hash."""
    p = Path(path)
    idx = p / "index.json"
    if idx.is_file():
        index = json.loads(idx.read_text())
        return {"path": p.name, "seed": index.get("seed"), "frames": index.get("num_frames"),
                "generator_version": generator_version(index)}
    if p.is_file():
        return {"path": p.name, "sha256": sha256_file(p)}
    return {"path": p.name}


def generator_version(index: dict[str, Any]) -> str:
    """The generator's identity for a data set index: shard format, the generator's own version
    when the index records one (``generator_version``), and a hash of the generator config (what
    a frame seed is rendered with)."""
    code = f"+gen:{index['generator_version']}" if index.get("generator_version") is not None else ""
    return f"{index.get('format', 'unknown')}{code}+cfg:{sha256_json(index.get('config'))[:12]}"


def utc_now() -> str:
    """Current UTC time, ISO 8601 with seconds."""
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()


def make_provenance(
    phase: str,
    recipe: str | None = None,
    recipe_sha256: str | None = None,
    data: list[dict[str, Any]] | None = None,
    parents: list[dict[str, Any]] | None = None,
    metrics: dict[str, Any] | None = None,
    world_size: int = 1,
    **extra: Any,
) -> dict[str, Any]:
    """A provenance block (see the module docstring) for weights written now."""
    out = {
        "git_commit": git_commit(),
        "recipe": recipe,
        "recipe_sha256": recipe_sha256,
        "phase": phase,
        "data": list(data or []),
        "parents": list(parents or []),
        "metrics": dict(metrics or {}),
        "torch_version": str(torch.__version__),  # TorchVersion is a str subclass weights_only refuses
        "created_utc": utc_now(),
        "world_size": int(world_size),
        "reconstructed": False,
    }
    out.update(extra)
    return plain(out)
