"""Run a recipe's phases in order, each resumable, each writing weights with provenance.

Layout under ``out``::

    recipe.json                 the resolved recipe of the last run (inheritance applied, its sha256)
    cache/                      frustum caches (content-keyed, shared by the phases)
    <phase>/phase.json          the phase's key (hash of everything that decides its result)
    <phase>/checkpoint.pt ...   the run (see :mod:`.train`)
    <phase>/result.json         written when the phase finished: result file, its sha256, seconds

A phase whose ``result.json`` carries the current key (and whose result file still has the
recorded sha256) is skipped; one with a checkpoint under the current key resumes; one whose
key changed (recipe, data, parents or code version) starts again.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path
from typing import Any

from . import distributed as ddp
from .data_cache import data_identity, ensure_dataset, frustum_config, frustum_key, get_frustums
from ..digests import sha256_file, sha256_json
from .provenance import dataset_identity, make_provenance
from .recipe import classifier_train_config, deep_merge, phase_train_config

#: bump when the training code changes what a phase computes from the same inputs
PHASE_CODE_VERSION = 1
_RUN_FILES = ("checkpoint.pt", "weights.pt", "best.pt", "result.json", "val_metrics.json", "classifier.pt",
              "pruned.pt", "adopted.pt")


class Stopped(Exception):
    """A time budget stopped a phase; running the recipe again continues it."""


def phase_result(out: Path, name: str) -> dict[str, Any] | None:
    """The ``result.json`` of a finished phase, else None."""
    p = Path(out) / name / "result.json"
    return json.loads(p.read_text()) if p.is_file() else None


def _is_done(out: Path, name: str, key: str) -> bool:
    res = phase_result(out, name)
    if res is None or res.get("phase_key") != key:
        return False
    f = Path(out) / name / res["file"]
    return f.is_file() and sha256_file(f) == res["sha256"]


def _prepare_phase_dir(d: Path, key: str, say: Callable[[str], None]) -> bool:
    """Make ``d`` the phase's directory for ``key``; returns whether a checkpoint can resume."""
    d.mkdir(parents=True, exist_ok=True)
    pj = d / "phase.json"
    old = json.loads(pj.read_text()).get("phase_key") if pj.is_file() else None
    if old != key:
        if old is not None:
            say(f"{d.name}: recipe, data or parents changed since the last run; starting the phase again")
        for f in _RUN_FILES:
            (d / f).unlink(missing_ok=True)
    pj.write_text(json.dumps({"phase_key": key}, indent=1))
    return old == key and (d / "checkpoint.pt").is_file()


def _parents(out: Path, names: list[str]) -> list[dict[str, Any]]:
    parents = []
    for n in names:
        res = phase_result(out, n)
        if res is None:
            raise RuntimeError(f"phase {n!r} has not finished (run the recipe without --phase, or that phase first)")
        parents.append({"phase": n, "file": f"{n}/{res['file']}", "sha256": res["sha256"]})
    return parents


def _on_rank0_first(env: ddp.DistEnv, fn: Callable[[], Any]) -> Any:
    """``fn`` on rank 0, then on the other ranks (who then find what rank 0 wrote)."""
    if env.is_main:
        v = fn()
        ddp.barrier(env)
        return v
    ddp.barrier(env)
    return fn()


def _frustum_sets(r: dict[str, Any], names: list[str], data_root: Path, cache: Path, cfg, env,
                  say: Callable[[str], None]) -> tuple[list[dict], list[str]]:
    """The frustum sets ``names`` (built or cached; extraction = the phase's ``data`` settings
    with the set's ``extract`` over them) and their content keys."""
    sets, keys = [], []
    num_points = cfg.model_config().num_points
    for n in names:
        spec = r["frustums"][n]
        ds_name = spec["dataset"]
        src = _on_rank0_first(env, partial(ensure_dataset, data_root, ds_name, r["datasets"][ds_name], say=say))
        tag = spec.get("tag", "train")
        extract = deep_merge(cfg.data, spec.get("extract", {}))
        keys.append(frustum_key(src, frustum_config(extract, num_points, tag), spec.get("max_frames")))
        sets.append(_on_rank0_first(env, partial(get_frustums, src, extract, num_points, cache, tag,
                                                 spec.get("max_frames"), say=say)))
    return sets, keys


def run_network_phase(r: dict[str, Any], ph: dict[str, Any], out: Path, data_root: Path, device,
                      max_minutes: float | None, say: Callable[[str], None]) -> dict[str, Any] | None:
    """Train one network phase (or skip it when done); returns its result record."""
    from . import frustum_dataset as fds
    from .train import train

    env = ddp.current()
    cfg = phase_train_config(r, ph)
    cache = out / "cache"
    tr_sets, tr_keys = _frustum_sets(r, list(ph["train_data"]), data_root, cache, cfg, env, say)
    va_sets, va_keys = _frustum_sets(r, [ph["val_data"]], data_root, cache, cfg, env, say) \
        if ph.get("val_data") else ([None], [None])
    parents = _parents(out, [ph["init"]] if ph.get("init") else [])
    phase_names = {p["name"] for p in r["phases"]}
    teacher = _parents(out, [cfg.teacher]) if cfg.teacher and cfg.teacher in phase_names else []
    key = sha256_json({"phase": {k: v for k, v in ph.items() if k != "comment"}, "train_config": cfg.to_dict(),
                       "frustums": tr_keys + va_keys, "parents": [p["sha256"] for p in parents + teacher],
                       "code": PHASE_CODE_VERSION})
    if teacher:  # after the key: the key holds the teacher's sha256, not where this run directory is
        cfg = replace(cfg, teacher=str(out / teacher[0]["file"]))
    d = out / ph["name"]
    if _is_done(out, ph["name"], key):
        say(f"phase {ph['name']}: done (result {phase_result(out, ph['name'])['file']}, key matches); skipped")
        return phase_result(out, ph["name"])
    resume = _on_rank0_first(env, lambda: _prepare_phase_dir(d, key, say) if env.is_main else
                             (d / "checkpoint.pt").is_file())
    data_sets = sorted({r["frustums"][n]["dataset"] for n in list(ph["train_data"]) + [ph.get("val_data")] if n})
    prov = make_provenance(ph["name"], recipe=r["file"], recipe_sha256=r["sha256"], parents=parents + teacher,
                           data=[{**dataset_identity(data_root / n), "path": n} for n in data_sets],
                           world_size=env.world_size, phase_key=key, seed=int(ph.get("seed", 0)))
    train_ds = tr_sets[0] if len(tr_sets) == 1 else fds.concat(tr_sets)
    say(f"phase {ph['name']}: {'resuming' if resume else 'training'} ({cfg.epochs} epochs, lr {cfg.lr}, "
        f"trainable {cfg.trainable or 'all'})")
    t0 = time.time()
    init = out / parents[0]["file"] if parents else None
    final = train(cfg, train_ds, va_sets[0], d, seed=int(ph.get("seed", 0)), device=device, resume=resume,
                  max_minutes=max_minutes, print_fn=say, init_weights=init, provenance=prov,
                  extra_meta={"phase": ph["name"], "recipe": r["file"]})
    if final.get("stopped_early"):
        raise Stopped(ph["name"])
    return _on_rank0_first(env, lambda: _write_result(d, ph.get("keep", "best"), key, time.time() - t0)
                           if env.is_main else phase_result(out, ph["name"]))


def run_prune_phase(r: dict[str, Any], ph: dict[str, Any], out: Path, data_root: Path,
                    say: Callable[[str], None]) -> dict[str, Any]:
    """Prune phase ``network``'s weights to ``widths`` (:mod:`.prune`), channels scored on
    ``frustums`` frustums of each of the ``score_data`` sets; writes ``pruned.pt``."""
    from ..model.io import load_weights, save_weights
    from .prune import prune_on, pruned_meta

    env = ddp.current()
    cfg = phase_train_config(r, {})  # the recipe's defaults: the extraction and point count its network phases use
    sets, set_keys = _frustum_sets(r, list(ph["score_data"]), data_root, out / "cache", cfg, env, say)
    parents = _parents(out, [ph["network"]])
    key = sha256_json({"phase": {k: v for k, v in ph.items() if k != "comment"}, "frustums": set_keys,
                       "parents": [p["sha256"] for p in parents], "code": PHASE_CODE_VERSION})
    d = out / ph["name"]
    if not env.is_main:
        ddp.barrier(env)
        return phase_result(out, ph["name"]) or {}
    try:
        if _is_done(out, ph["name"], key):
            say(f"phase {ph['name']}: done (key matches); skipped")
            return phase_result(out, ph["name"]) or {}
        _prepare_phase_dir(d, key, say)
        t0 = time.time()
        src = out / parents[0]["file"]
        model, meta = load_weights(src)
        pruned, _ = prune_on(model, sets, dict(ph["widths"]), int(ph.get("frustums", 600)), int(ph.get("seed", 0)))
        data_sets = sorted({r["frustums"][n]["dataset"] for n in ph["score_data"]})
        prov = make_provenance(ph["name"], recipe=r["file"], recipe_sha256=r["sha256"], parents=parents,
                               data=[{**dataset_identity(data_root / n), "path": n} for n in data_sets],
                               phase_key=key, seed=int(ph.get("seed", 0)))
        meta = {**pruned_meta(meta, src, ph["widths"]), "phase": ph["name"], "recipe": r["file"]}
        save_weights(pruned, d / "pruned.pt", meta=meta, provenance=prov)
        say(f"phase {ph['name']}: {sum(p.numel() for p in model.parameters()):,} -> "
            f"{sum(p.numel() for p in pruned.parameters()):,} parameters")
        res = {"file": "pruned.pt", "sha256": sha256_file(d / "pruned.pt"), "phase_key": key,
               "seconds": round(time.time() - t0, 1)}
        (d / "result.json").write_text(json.dumps(res, indent=1))
        return res
    finally:
        ddp.barrier(env)


def _write_result(d: Path, keep: str, key: str, seconds: float) -> dict[str, Any]:
    name = "best.pt" if keep == "best" and (d / "best.pt").is_file() else "weights.pt"
    res = {"file": name, "sha256": sha256_file(d / name), "phase_key": key, "seconds": round(seconds, 1)}
    (d / "result.json").write_text(json.dumps(res, indent=1))
    return res


def run_classifier_phase(r: dict[str, Any], ph: dict[str, Any], out: Path, data_root: Path,
                         say: Callable[[str], None]) -> dict[str, Any] | None:
    """Train the proposal classifier on the candidates of phase ``network``'s weights (rank 0
    only: the classifier is small; the other ranks wait)."""
    env = ddp.current()
    if not env.is_main:
        ddp.barrier(env)
        return phase_result(out, ph["name"])
    try:
        return _classifier_phase(r, ph, out, data_root, say)
    finally:
        ddp.barrier(env)


def _proposer_identity() -> dict[str, str | None]:
    """sha256 of the packaged learned 2D proposer and of its int8 version, and the name of the
    one the candidates are built with (the candidates of a learned or hybrid classifier phase
    depend on them; None where a file is missing)."""
    from ..proposals.learned import DEFAULT_MODEL, model_file
    from ..proposals.learned_int8 import int8_path

    out: dict[str, str | None] = {name: sha256_file(p) if p.is_file() else None
                                  for name, p in (("onnx", DEFAULT_MODEL), ("int8", int8_path(DEFAULT_MODEL)))}
    out["runs"] = model_file(DEFAULT_MODEL).name
    return out


def _classifier_phase(r: dict[str, Any], ph: dict[str, Any], out: Path, data_root: Path,
                      say: Callable[[str], None]) -> dict[str, Any]:
    from .classifier_cli import build_all, load_candidates
    from .train_classifier import train_classifier

    srcs = [ensure_dataset(data_root, n, r["datasets"][n], say=say) for n in ph["datasets"]]
    parents = _parents(out, [ph["network"]])
    cfg = classifier_train_config(r, ph)
    train_d = asdict(cfg)
    # the workers split each data set's shards into that many candidate files: part of the key,
    # so that a cache never mixes two splits; the proposer only when not the default, so that
    # geometric caches keep their keys
    source = ph.get("proposal_source", "geometric")
    cand_id = {"network": parents[0]["sha256"], "data": [data_identity(s) for s in srcs],
               "proposals": ph.get("proposals", 20), "max_frames": ph.get("max_frames"),
               "workers": int(ph.get("workers", 2))}
    if source != "geometric":
        cand_id["proposal_source"] = source
        cand_id["proposer"] = _proposer_identity()
    cand_key = sha256_json(cand_id)[:16]
    key = sha256_json({"phase": {k: v for k, v in ph.items() if k != "comment"}, "train": train_d,
                       "candidates": cand_key, "code": PHASE_CODE_VERSION})
    d = out / ph["name"]
    if _is_done(out, ph["name"], key):
        say(f"phase {ph['name']}: done (key matches); skipped")
        return phase_result(out, ph["name"]) or {}
    _prepare_phase_dir(d, key, say)
    t0 = time.time()
    paths = build_all(srcs, out / "cache" / f"candidates_{cand_key}", out / parents[0]["file"], ph.get("max_frames"),
                      int(ph.get("workers", 2)), int(ph.get("proposals", 20)), source)
    prov = make_provenance(ph["name"], recipe=r["file"], recipe_sha256=r["sha256"], parents=parents,
                           data=[{**dataset_identity(s), "path": s.name} for s in srcs], phase_key=key,
                           seed=cfg.seed)
    result = train_classifier(load_candidates(paths), d / "classifier.pt", cfg, log=say, provenance=prov)
    say(f"phase {ph['name']}: best epoch {result['best'].get('epoch')}")
    res = {"file": "classifier.pt", "sha256": sha256_file(d / "classifier.pt"), "phase_key": key,
           "seconds": round(time.time() - t0, 1)}
    (d / "result.json").write_text(json.dumps(res, indent=1))
    return res


def run_recipe(r: dict[str, Any], out: str | Path, data_root: str | Path, only: list[str] | None = None,
               device="cpu", max_minutes: float | None = None, say: Callable[[str], None] = print) -> list[dict]:
    """Run the phases of the resolved recipe ``r`` in order (``only``: just those, whose
    parents must have finished). Returns the result records; raises :class:`Stopped` when
    the time budget ran out (run again to continue)."""
    out, data_root = Path(out), Path(data_root)
    unknown = sorted(set(only or []) - {ph["name"] for ph in r["phases"]})
    if unknown:
        raise ValueError(f"no phase {unknown} in {r['file']} (phases: {[ph['name'] for ph in r['phases']]})")
    out.mkdir(parents=True, exist_ok=True)
    if ddp.current().is_main:  # what this run directory was last run with (inheritance resolved)
        (out / "recipe.json").write_text(json.dumps(r, indent=1))
    t_start = time.time()
    results = []
    for ph in r["phases"]:
        if only and ph["name"] not in only:
            continue
        left = None if max_minutes is None else max_minutes - (time.time() - t_start) / 60.0
        if left is not None and left <= 0:
            raise Stopped(ph["name"])
        if ph.get("kind", "network") == "classifier":
            res = run_classifier_phase(r, ph, out, data_root, say)
        elif ph.get("kind") == "prune":
            res = run_prune_phase(r, ph, out, data_root, say)
        else:
            res = run_network_phase(r, ph, out, data_root, device, left, say)
        results.append({"phase": ph["name"], **(res or {})})
    return results


def export(r: dict[str, Any], out: str | Path, dest: str | Path, say: Callable[[str], None] = print) -> list[Path]:
    """Copy the results the recipe's ``exports`` name (file name -> phase) into ``dest``."""
    written = []
    for fname, ph_name in r.get("exports", {}).items():
        res = phase_result(Path(out), ph_name)
        if res is None:
            raise RuntimeError(f"export {fname}: phase {ph_name!r} has not finished")
        target = Path(dest) / fname
        shutil.copyfile(Path(out) / ph_name / res["file"], target)
        say(f"exported {ph_name}/{res['file']} -> {target}")
        written.append(target)
    return written


def adopt(r: dict[str, Any], out: str | Path, files: list[Path], say: Callable[[str], None] = print) -> list[str]:
    """Take weights files written by the recipe runner (the packaged ones, say) as the results
    of the phases their provenance names, where those phases have no result in ``out``: the
    phases after them can then run without training everything before. A file's provenance
    must name this recipe (or one it inherits) and one of its phases; its phase key is kept
    (none in reconstructed provenance), so a full run still retrains a phase whose inputs
    differ. Returns the adopted phases."""
    from ..model.io import read_blob

    out = Path(out)
    names = {ph["name"] for ph in r["phases"]}
    adopted = []
    for f in map(Path, files):
        blob = read_blob(f)
        prov = (blob.get("meta") or {}).get("provenance") or blob.get("provenance") or {}
        ph_name = str(prov.get("phase"))
        recipe = Path(str(prov.get("recipe"))).name  # older files name the recipe by its path
        if recipe not in r.get("lineage", [r["file"]]) or ph_name not in names:
            raise ValueError(f"{f}: its provenance names recipe {prov.get('recipe')!r}, phase {ph_name!r}: "
                             f"not a phase of {r['file']} (or a recipe it inherits) written by the recipe runner")
        if phase_result(out, ph_name) is not None:
            say(f"{f}: phase {ph_name} already has a result in {out}; not adopted")
            continue
        d = out / ph_name
        d.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, d / "adopted.pt")
        key = prov.get("phase_key")  # None in reconstructed provenance: a full run retrains that phase
        (d / "phase.json").write_text(json.dumps({"phase_key": key}, indent=1))
        res = {"file": "adopted.pt", "sha256": sha256_file(d / "adopted.pt"), "phase_key": key,
               "seconds": 0.0, "adopted_from": str(f)}
        (d / "result.json").write_text(json.dumps(res, indent=1))
        say(f"adopted {f} as the result of phase {ph_name}")
        adopted.append(ph_name)
    return adopted
