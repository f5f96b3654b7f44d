"""Training recipes as data: JSON files that list the phases of a training.

A recipe file may say ``"inherits": "base.json"`` (a path relative to itself): the base is
loaded first (recursively) and the file deep-merged over it (dicts merge key by key, any
other value, lists included, replaces). The resolved recipe has::

    datasets      name -> {"seed", "frames", "frames_per_shard", "rgb_format", "synth": {SynthConfig}}
    frustums      name -> {"dataset": name, "extract": {FrustumDatasetConfig overrides},
                           "tag": "train" | "val"}
    defaults      TrainConfig fields shared by every network phase
    phase_overrides  TrainConfig fields merged over every network phase's own (tiny test runs)
    classifier_overrides  ClassifierTrainConfig fields merged over every classifier phase's own
    exports       file name -> phase whose result ``--export DIR`` copies there
    phases        [phase, ...] in training order (a file's ``append_phases`` go after the
                  phases it inherits: a recipe that continues its base)

A network phase: ``name``; ``init`` (an earlier phase, or null for a fresh network);
``train_data`` (frustum set names, concatenated); ``val_data`` (one frustum set);
``seed``; ``keep`` ("best": the best validation epoch's weights, or "last"); ``train``
(TrainConfig fields over ``defaults``: model, epochs, lr, trainable parts, tasks, threads).
A classifier phase (``"kind": "classifier"``): ``network`` (the phase whose weights propose
and first-pass the candidates), ``datasets``, ``seed``, ``proposals``, ``proposal_source``
(the built-in proposer, default ``geometric``), ``workers``, ``train`` (ClassifierTrainConfig fields).
A prune phase (``"kind": "prune"``, :mod:`.prune`): ``network`` (an earlier phase), ``widths``
(PointNet name -> channels its last layer keeps), ``score_data`` (frustum sets the channels are
scored on), ``frustums`` (drawn from each, default 600), ``seed``. A network phase's
``teacher`` may name an earlier phase (distillation from that phase's result).
Nothing in a recipe is a wall-clock budget.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

from .config import TrainConfig
from ..detector_config import BUILTIN_PROPOSAL_SOURCES
from ..digests import sha256_json

RECIPES_DIR = Path(__file__).resolve().parent / "recipes"
_PHASE_KEYS = {"name", "kind", "comment", "init", "train_data", "val_data", "seed", "keep", "train",
               "network", "datasets", "proposals", "proposal_source", "workers", "max_frames",
               "widths", "score_data", "frustums"}


def deep_merge(base: Any, over: Any) -> Any:
    """``over`` merged into a copy of ``base``: dicts key by key, anything else replaced."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = copy.deepcopy(base)
        for k, v in over.items():
            out[k] = deep_merge(out[k], v) if k in out else copy.deepcopy(v)
        return out
    return copy.deepcopy(over)


def _load_raw(path: Path, seen: tuple[Path, ...], lineage: list[str] | None = None) -> dict[str, Any]:
    path = path.resolve()
    if lineage is not None:
        lineage.append(path.name)
    if path in seen:
        raise ValueError(f"recipe inheritance loops through {path}")
    if not path.is_file():
        raise FileNotFoundError(f"no recipe file {path}")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from e
    parent = d.pop("inherits", None)
    more = d.pop("append_phases", [])
    out = d if parent is None else deep_merge(_load_raw((path.parent / parent), seen + (path,), lineage), d)
    out["phases"] = list(out.get("phases", [])) + list(more)
    return out


def resolve_path(name: str | Path) -> Path:
    """A recipe file by path, or by name under the packaged ``recipes/`` folder."""
    p = Path(name)
    if p.is_file():
        return p
    for cand in (RECIPES_DIR / p, RECIPES_DIR / f"{p}.json"):
        if cand.is_file():
            return cand
    packaged = sorted(f.stem for f in RECIPES_DIR.glob("*.json"))
    raise FileNotFoundError(f"no recipe {name!r}: neither a file nor a packaged recipe ({', '.join(packaged)})")


def load_recipe(path: str | Path) -> dict[str, Any]:
    """The resolved recipe (inheritance applied, checked); ``sha256`` holds the hash of its
    resolved content, ``file`` its file name and ``lineage`` the names of it and its bases."""
    p = resolve_path(path)
    lineage: list[str] = []
    r = _load_raw(p, (), lineage)
    r.setdefault("datasets", {})
    r.setdefault("frustums", {})
    r.setdefault("defaults", {})
    r.setdefault("phase_overrides", {})
    r.setdefault("phases", [])
    check(r)
    r["sha256"] = sha256_json({k: v for k, v in r.items() if k not in ("comment", "description")})
    r["file"] = p.name
    r["lineage"] = lineage  # this file, then the files it inherits from
    return r


def check(r: dict[str, Any]) -> None:
    """Refuse a recipe whose phases name unknown phases, data or settings (one clear error)."""
    names: list[str] = []
    all_names = {ph.get("name") for ph in r["phases"]}
    for ph in r["phases"]:
        name = ph.get("name")
        if not name or name in names:
            raise ValueError(f"phase names must be unique and non-empty: {name!r}")
        bad = set(ph) - _PHASE_KEYS
        if bad:
            raise ValueError(f"phase {name}: unknown keys {sorted(bad)}")
        if ph.get("kind", "network") == "classifier":
            _refs(ph, "network", [ph.get("network")], names, "an earlier phase")
            _refs(ph, "datasets", ph.get("datasets"), r["datasets"], "a known data set")
            if ph.get("proposal_source", "geometric") not in BUILTIN_PROPOSAL_SOURCES:
                raise ValueError(f"phase {name}: proposal_source must be one of {BUILTIN_PROPOSAL_SOURCES}")
            classifier_train_config(r, ph)  # unknown ClassifierTrainConfig keys fail here
        elif ph.get("kind") == "prune":
            _check_prune(r, ph, names)
        elif ph.get("kind", "network") != "network":
            raise ValueError(f"phase {name}: kind must be 'network', 'classifier' or 'prune', not {ph['kind']!r}")
        else:
            if ph.get("init") is not None and ph["init"] not in names:
                raise ValueError(f"phase {name}: init {ph['init']!r} is not an earlier phase")
            _refs(ph, "train_data", ph.get("train_data"), r["frustums"], "a known frustum set")
            if ph.get("val_data") is not None:
                _refs(ph, "val_data", [ph["val_data"]], r["frustums"], "a known frustum set")
            if ph.get("keep", "best") not in ("best", "last"):
                raise ValueError(f"phase {name}: keep must be 'best' or 'last'")
            teacher = phase_train_config(r, ph).teacher  # unknown TrainConfig keys fail here
            if teacher in all_names and teacher not in names:
                raise ValueError(f"phase {name}: teacher {teacher!r} is not an earlier phase")
        names.append(name)
    for fname, f in r["frustums"].items():
        if f.get("dataset") not in r["datasets"]:
            raise ValueError(f"frustum set {fname}: unknown data set {f.get('dataset')!r}")
    for fname, ph_name in r.get("exports", {}).items():
        if ph_name not in names:
            raise ValueError(f"export {fname}: {ph_name!r} is not a phase")


def _check_prune(r: dict[str, Any], ph: dict[str, Any], names: list[str]) -> None:
    from .prune import PRUNABLE

    name = ph["name"]
    _refs(ph, "network", [ph.get("network")], names, "an earlier phase")
    widths = ph.get("widths")
    if not isinstance(widths, dict) or not widths:
        raise ValueError(f"phase {name}: widths must map PointNet names to channel counts")
    for k, w in widths.items():
        if k not in PRUNABLE or not isinstance(w, int) or w < 1:
            raise ValueError(f"phase {name}: width {k}={w!r}: expected a positive integer for one of {sorted(PRUNABLE)}")
    _refs(ph, "score_data", ph.get("score_data"), r["frustums"], "a known frustum set")


def _refs(ph: dict[str, Any], key: str, items: Any, known: Any, what: str) -> None:
    """Refuse a phase whose ``key`` lists nothing or something not in ``known``."""
    if not items:
        raise ValueError(f"phase {ph['name']}: no {key}")
    for x in items:
        if x not in known:
            raise ValueError(f"phase {ph['name']}: {key} {x!r} is not {what}")


def phase(r: dict[str, Any], name: str) -> dict[str, Any]:
    """The phase called ``name``."""
    for ph in r["phases"]:
        if ph["name"] == name:
            return ph
    raise KeyError(f"no phase {name!r} (phases: {[p['name'] for p in r['phases']]})")


def phase_train_config(r: dict[str, Any], ph: dict[str, Any]) -> TrainConfig:
    """A network phase's TrainConfig: ``defaults``, the phase's ``train``, then ``phase_overrides``."""
    d = deep_merge(deep_merge(r["defaults"], ph.get("train", {})), r["phase_overrides"])
    return TrainConfig.from_dict(d)


def classifier_train_config(r: dict[str, Any], ph: dict[str, Any]):
    """A classifier phase's ClassifierTrainConfig: its ``train``, then ``classifier_overrides``;
    the seed is the phase's."""
    from .train_classifier import ClassifierTrainConfig

    d = {**ph.get("train", {}), **r.get("classifier_overrides", {}), "seed": int(ph.get("seed", 0))}
    bad = set(d) - set(ClassifierTrainConfig.__dataclass_fields__)
    if bad:
        raise ValueError(f"phase {ph['name']}: unknown classifier training keys {sorted(bad)}")
    return ClassifierTrainConfig(**d)
