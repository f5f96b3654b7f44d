"""Training recipes: inheritance and checks, content-keyed caches, provenance, and a whole tiny
recipe run end to end (every phase's weights with provenance, the same weights from the same
seeds, a finished recipe not run again)."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import pytest
import torch

from shape_detector.model.io import read_blob
from shape_detector.training import recipe as rcp
from shape_detector.training.data_cache import data_identity, frustum_config, frustum_key
from shape_detector.digests import sha256_file

TINY = Path(__file__).resolve().parent / "data" / "tiny_recipe.json"
WEIGHTS = Path(__file__).resolve().parents[1] / "shape_detector" / "weights"
#: provenance keys every weights file written by a recipe carries
PROVENANCE_KEYS = {"git_commit", "recipe", "recipe_sha256", "phase", "data", "parents", "metrics", "torch_version",
                   "created_utc", "world_size", "reconstructed"}


def _write(path: Path, d: dict) -> Path:
    path.write_text(json.dumps(d))
    return path


def test_inheritance_merges_dicts_and_replaces_the_rest(tmp_path):
    base = _write(tmp_path / "base.json", {
        "datasets": {"train": {"seed": 1, "frames": 10}},
        "frustums": {"gt": {"dataset": "train", "extract": {}}},
        "defaults": {"epochs": 3, "lr": 0.1, "model": {"num_points": 64, "seg_widths": [8, 8]}},
        "phases": [{"name": "a", "train_data": ["gt"]}],
    })
    child = _write(tmp_path / "child.json", {
        "inherits": "base.json",
        "defaults": {"lr": 0.01, "model": {"seg_widths": [4]}},
        "phases": [{"name": "b", "train_data": ["gt"], "train": {"epochs": 5}}],
    })
    r = rcp.load_recipe(child)
    assert r["defaults"]["epochs"] == 3 and r["defaults"]["lr"] == 0.01
    assert r["defaults"]["model"] == {"num_points": 64, "seg_widths": [4]}  # lists replace
    assert [p["name"] for p in r["phases"]] == ["b"]
    cfg = rcp.phase_train_config(r, r["phases"][0])
    assert cfg.epochs == 5 and cfg.lr == pytest.approx(0.01) and cfg.model_config().num_points == 64
    assert r["file"] == "child.json" and len(r["sha256"]) == 64
    # the hash is of the resolved content: a comment does not change it, a setting does
    _write(child, {**json.loads(child.read_text()), "comment": "words"})
    assert rcp.load_recipe(child)["sha256"] == r["sha256"]
    _write(base, {**json.loads(base.read_text()), "defaults": {"epochs": 4}})
    assert rcp.load_recipe(child)["sha256"] != r["sha256"]


@pytest.mark.parametrize("phases, message", [
    ([{"name": "a", "train_data": ["nope"]}], "not a known frustum set"),
    ([{"name": "a", "init": "b", "train_data": ["gt"]}], "not an earlier phase"),
    ([{"name": "a", "train_data": ["gt"]}, {"name": "a", "train_data": ["gt"]}], "unique"),
    ([{"name": "a", "train_data": ["gt"], "epochs": 3}], "unknown keys"),
    ([{"name": "a", "train_data": ["gt"], "train": {"epoch": 3}}], "unknown training config keys"),
    ([{"name": "a", "train_data": ["gt"], "keep": "first"}], "keep"),
    ([{"name": "a", "train_data": []}], "no train_data"),
    ([{"name": "c", "kind": "classifier", "network": "x", "datasets": ["train"]}], "not an earlier phase"),
    ([{"name": "a", "train_data": ["gt"]},
      {"name": "c", "kind": "classifier", "network": "a", "datasets": ["train"], "train": {"epoch": 2}}],
     "unknown classifier training keys"),
    ([{"name": "a", "train_data": ["gt"]}, {"name": "c", "kind": "classifier", "network": "a"}], "no datasets"),
    ([{"name": "a", "train_data": ["gt"]}, {"name": "c", "kind": "classifier", "network": "a", "datasets": ["train"],
                                            "proposal_source": "external"}], "proposal_source"),
    ([{"name": "a", "kind": "other", "train_data": ["gt"]}], "kind"),
])
def test_bad_recipes_are_refused_with_one_clear_error(tmp_path, phases, message):
    p = _write(tmp_path / "r.json", {"datasets": {"train": {"seed": 1, "frames": 2}},
                                     "frustums": {"gt": {"dataset": "train"}}, "phases": phases})
    with pytest.raises(ValueError, match=message):
        rcp.load_recipe(p)


def test_inheritance_loops_and_missing_files_are_refused(tmp_path):
    _write(tmp_path / "a.json", {"inherits": "b.json"})
    _write(tmp_path / "b.json", {"inherits": "a.json"})
    with pytest.raises(ValueError, match="loops"):
        rcp.load_recipe(tmp_path / "a.json")
    with pytest.raises(FileNotFoundError):
        rcp.load_recipe(tmp_path / "none.json")
    _write(tmp_path / "e.json", {"datasets": {"t": {"seed": 1, "frames": 2}}, "frustums": {"gt": {"dataset": "t"}},
                                 "phases": [{"name": "a", "train_data": ["gt"]}], "exports": {"x.pt": "b"}})
    with pytest.raises(ValueError, match="export x.pt"):
        rcp.load_recipe(tmp_path / "e.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        rcp.load_recipe(tmp_path / "bad.json")


def test_shipped_recipe_resolves_by_name_and_exports_the_shipped_files():
    r = rcp.load_recipe("shipped")
    assert r["file"] == "shipped.json" and r == rcp.load_recipe(rcp.RECIPES_DIR / "shipped.json")
    assert set(r["exports"]) == {"default.pt", "classifier.pt", "classifier_hybrid.pt"}
    names = [p["name"] for p in r["phases"]]
    assert all(v in names for v in r["exports"].values())
    # every phase's epochs are in the recipe; nothing is a wall-clock budget
    assert "max_minutes" not in json.dumps(r)
    for ph in r["phases"]:
        if ph.get("kind") != "classifier":
            assert rcp.phase_train_config(r, ph).epochs >= 1


def test_frustum_cache_key_follows_content_not_paths(tmp_path):
    """A generated data set is identified by its seed, frame count and generator version: a
    copy elsewhere has the same key; another extraction setting has another."""
    src = tmp_path / "a" / "train"
    src.mkdir(parents=True)
    index = {"format": "shape_detector.synth shards v1", "seed": 5, "num_frames": 3, "config": {"width": 320}}
    _write(src / "index.json", index)
    moved = tmp_path / "b" / "elsewhere"
    shutil.copytree(src, moved)
    cfg = frustum_config({}, 128, "train")
    assert data_identity(src) == data_identity(moved) and "path" not in data_identity(src)
    assert frustum_key(src, cfg, None) == frustum_key(moved, cfg, None)
    assert frustum_key(src, frustum_config({"augment_copies": 3}, 128, "train"), None) != frustum_key(src, cfg, None)
    assert frustum_key(src, frustum_config({}, 128, "val"), None) != frustum_key(src, cfg, None)
    _write(moved / "index.json", {**index, "config": {"width": 640}})  # another generator config
    assert frustum_key(src, cfg, None) != frustum_key(moved, cfg, None)
    _write(moved / "index.json", {**index, "generator_version": 2})  # a generator that renders otherwise
    assert frustum_key(src, cfg, None) != frustum_key(moved, cfg, None)


def test_hybrid_classifier_candidates_follow_the_packaged_proposer(tmp_path, monkeypatch):
    """A learned / hybrid classifier phase's candidates come from the packaged 2D proposer: its
    files are part of their key, so a retrained proposer retrains the phase."""
    from shape_detector.proposals import learned
    from shape_detector.training import runner

    model = tmp_path / "proposer2d.onnx"
    monkeypatch.setattr(learned, "DEFAULT_MODEL", model)
    assert runner._proposer_identity() == {"onnx": None, "int8": None, "runs": "proposer2d.onnx"}
    model.write_bytes(b"a")
    first = runner._proposer_identity()
    assert first["onnx"] == sha256_file(model) and first["int8"] is None
    (tmp_path / "proposer2d.int8.onnx").write_bytes(b"b")
    model.write_bytes(b"c")
    second = runner._proposer_identity()
    assert second["onnx"] != first["onnx"] and second["int8"] is not None
    assert second["runs"] == "proposer2d.onnx"  # candidates come from the float32 network (precision auto)


def _make_weights_recipe() -> str:
    """The recipe ``make weights`` runs (the Makefile's ``RECIPE``)."""
    import re

    text = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    return re.search(r"^RECIPE \?= (\S+)$", text, re.M).group(1)


#: default.pt and classifier_hybrid.pt were written by the recipe runner; classifier.pt predates recipes
#: (provenance written after)
@pytest.mark.parametrize(("name", "reconstructed"),
                         [("default.pt", False), ("classifier.pt", True), ("classifier_hybrid.pt", False)])
def test_shipped_weights_carry_provenance(name, reconstructed, capsys):
    from shape_detector.training import weights_info as wi

    parser = argparse.ArgumentParser()
    wi.configure_parser(parser)
    assert wi.main(parser.parse_args([str(WEIGHTS / name), "--json"])) == 0
    info = json.loads(capsys.readouterr().out)
    prov = info["provenance"]
    assert PROVENANCE_KEYS <= set(prov)
    assert len(prov["git_commit"].split("+")[0]) == 40
    assert prov["parents"] and all(len(p["sha256"]) == 64 for p in prov["parents"])
    # the shipped files name the recipe `make weights` runs (or one it inherits), their phase in it
    # and their parents' phases
    shipped = rcp.load_recipe(_make_weights_recipe())
    own = Path(prov["recipe"]).name
    assert own in shipped["lineage"] and shipped["exports"][name] == prov["phase"]
    assert prov["recipe_sha256"] == rcp.load_recipe(own)["sha256"]
    names = [p["name"] for p in shipped["phases"]]
    assert all(p["phase"] in names for p in prov["parents"])
    assert prov["reconstructed"] is reconstructed
    if reconstructed:
        assert prov["notes"]  # written after the fact, and says how
    assert info["sha256"] == sha256_file(WEIGHTS / name)
    assert wi.main(parser.parse_args([str(WEIGHTS / name)])) == 0
    assert ("provenance reconstructed" in capsys.readouterr().out) is reconstructed


def test_weights_info_refuses_what_is_not_a_weights_file(tmp_path, capsys):
    from shape_detector.training import weights_info as wi

    bad = tmp_path / "x.pt"
    bad.write_bytes(b"not a weights file")
    parser = argparse.ArgumentParser()
    wi.configure_parser(parser)
    assert wi.main(parser.parse_args([str(bad)])) == 2
    assert "weights-info" in capsys.readouterr().err


def _state(path: Path) -> dict[str, torch.Tensor]:
    return read_blob(path)["state_dict"]


def _run_cli(args: list[str]) -> int:
    from shape_detector.training import cli

    parser = argparse.ArgumentParser()
    cli.configure_parser(parser)
    return cli.main(parser.parse_args(args))


def _check_provenance(r: dict, out: Path) -> dict[str, str]:
    """Check every phase's weights provenance under ``out``; returns phase name -> weights file name."""
    files: dict[str, str] = {}
    for ph in r["phases"]:
        res = json.loads((out / ph["name"] / "result.json").read_text())
        files[ph["name"]] = res["file"]
        prov = read_blob(out / ph["name"] / res["file"])["provenance"]
        assert PROVENANCE_KEYS <= set(prov), ph["name"]
        assert prov["phase"] == ph["name"] and prov["recipe"] == TINY.name
        assert prov["recipe_sha256"] == r["sha256"] and prov["reconstructed"] is False
        assert prov["git_commit"] and prov["world_size"] == 1
        assert prov["data"] and all({"seed", "frames", "generator_version"} <= set(d) for d in prov["data"])
        assert {d["seed"] for d in prov["data"]} <= {s["seed"] for s in r["datasets"].values()}
        assert prov["metrics"], ph["name"]
        parent = ph.get("init") or ph.get("network")
        if parent is None:
            assert prov["parents"] == []
        else:
            (p,) = prov["parents"]
            assert p["phase"] == parent and p["sha256"] == sha256_file(out / parent / files[parent])
    return files


def _assert_same_weights(out_a: Path, out_b: Path, files: dict[str, str]) -> None:
    """Every phase's weights under ``out_b`` match those under ``out_a`` (same tensors, float tolerance)."""
    for n, fname in files.items():
        a, b = _state(out_a / n / fname), _state(out_b / n / fname)
        assert set(a) == set(b)
        for k in a:
            torch.testing.assert_close(b[k].float(), a[k].float(), atol=1e-6, rtol=1e-5, msg=f"{n}: {k}")


@pytest.mark.slow
def test_tiny_recipe_end_to_end_is_reproducible_and_resumable(tmp_path, monkeypatch):
    """The tiny recipe (a fresh network, a phase grown from it with the rest frozen, the
    proposal classifier on the grown network's candidates) on freshly generated data: every
    phase writes weights with provenance; a second run from the same seeds (data generated
    again elsewhere) gives the same weights, and so does one interrupted and resumed; running a
    finished recipe again trains nothing; a changed phase retrains itself and what follows."""
    from shape_detector.training.runner import run_recipe

    monkeypatch.setenv("SHAPE_DETECTOR_CACHE", str(tmp_path / "graph_cache"))
    r = rcp.load_recipe(TINY)
    out1, out2, export = tmp_path / "run1", tmp_path / "run2", tmp_path / "export"
    export.mkdir()
    assert _run_cli(["--recipe", str(TINY), "--data-root", str(tmp_path / "data1"), "--out", str(out1),
                     "--device", "cpu", "--export", str(export)]) == 0
    phases = [p["name"] for p in r["phases"]]
    files = _check_provenance(r, out1)
    for fname, ph in r["exports"].items():
        assert sha256_file(export / fname) == sha256_file(out1 / ph / files[ph])

    # a finished recipe: every phase skipped, nothing rewritten
    before = {n: sha256_file(out1 / n / files[n]) for n in phases}
    said: list[str] = []
    run_recipe(r, out1, tmp_path / "data1", say=said.append)
    assert sum("skipped" in s for s in said) == len(phases)
    assert not any("training" in s or "building" in s or "generating" in s for s in said), said
    assert {n: sha256_file(out1 / n / files[n]) for n in phases} == before

    # the same seeds again, from data generated again: the same weights (one thread, CPU)
    run_recipe(r, out2, tmp_path / "data2", say=lambda s: None)
    _assert_same_weights(out1, out2, files)

    # a phase interrupted after its first epoch resumes from its checkpoint and ends where an
    # uninterrupted run does
    from shape_detector.training import train as train_mod
    from shape_detector.training.runner import Stopped

    real_train = train_mod.train

    def one_epoch_then_stop(*args, **kwargs):
        final = real_train(*args, **{**kwargs, "stop_after_epochs": 1})
        return {**final, "stopped_early": True}

    out3 = tmp_path / "run3"
    monkeypatch.setattr(train_mod, "train", one_epoch_then_stop)
    with pytest.raises(Stopped):
        run_recipe(r, out3, tmp_path / "data2", say=lambda s: None)
    monkeypatch.setattr(train_mod, "train", real_train)
    said = []
    run_recipe(r, out3, tmp_path / "data2", say=said.append)
    assert any(s.startswith(f"phase {phases[0]}: resuming") for s in said), said
    _assert_same_weights(out1, out3, files)

    # a changed phase runs again with the phases after it, not those before
    changed = json.loads(TINY.read_text())
    changed["inherits"] = str(TINY.parent / changed["inherits"])
    changed["phases"][1]["train"]["lr"] = 0.001
    r2 = rcp.load_recipe(_write(tmp_path / "changed.json", changed))
    said = []
    run_recipe(r2, out1, tmp_path / "data1", say=said.append)
    skipped = [n for n in phases if any(s.startswith(f"phase {n}: done") for s in said)]
    assert skipped == [phases[0]], said


def test_cli_refuses_mixed_options_and_unknown_phases(tmp_path, capsys):
    assert _run_cli(["--recipe", str(TINY), "--epochs", "3", "--out", str(tmp_path / "o")]) == 2
    assert "--epochs" in capsys.readouterr().err
    assert _run_cli(["--data", str(tmp_path), "--out", str(tmp_path / "o"), "--export", str(tmp_path)]) == 2
    assert "--export" in capsys.readouterr().err
    assert _run_cli(["--recipe", str(TINY), "--phase", "nope", "--out", str(tmp_path / "o")]) == 2
    assert "no phase" in capsys.readouterr().err
    assert _run_cli(["--recipe", "no_such_recipe"]) == 2
    assert "shipped" in capsys.readouterr().err  # names the packaged recipes
    # weights of another recipe's phase are not adopted, and nothing runs
    assert _run_cli(["--recipe", str(TINY), "--out", str(tmp_path / "o"), "--data-root", str(tmp_path / "d"),
                     "--adopt", str(WEIGHTS / "default.pt")]) == 2
    assert "--adopt" in capsys.readouterr().err and not (tmp_path / "d").exists()


def test_a_spent_time_budget_stops_before_the_next_phase(tmp_path):
    """``--max-minutes`` stops a recipe (exit status 3, resumable); it never changes a phase."""
    from shape_detector.training.runner import Stopped, run_recipe

    with pytest.raises(Stopped):
        run_recipe(rcp.load_recipe(TINY), tmp_path / "o", tmp_path / "data", max_minutes=0.0, say=lambda s: None)
    assert not (tmp_path / "data").exists()  # stopped before generating anything
    assert _run_cli(["--recipe", str(TINY), "--out", str(tmp_path / "o"), "--data-root", str(tmp_path / "data"),
                     "--max-minutes", "0", "--device", "cpu"]) == 3


@pytest.mark.parametrize("name, width", [("shipped", 1.0), ("collapsed", 1.0), ("half_width", 0.5),
                                         ("half_width_distilled", 0.5), ("pruned", None)])
def test_every_phase_of_a_packaged_recipe_can_start_from_its_parent(name, width):
    """Each network phase of a packaged recipe accepts its parent's network (branches it adds
    start as no-ops, nothing else differs) and names parts its network has; the network it
    exports is the shipped architecture, every layer at ``width`` times the shipped width."""
    from shape_detector.model.network import FrustumShapeNet
    from shape_detector.training.init_from import freeze, load_init

    r = rcp.load_recipe(name)
    nets = {}
    for ph in r["phases"]:
        if ph.get("kind") == "classifier":
            assert ph["network"] in nets
            continue
        if ph.get("kind") == "prune":
            from shape_detector.training.prune import prune_network

            parent = nets[ph["network"]]
            scores = {n: torch.rand(getattr(parent, n).out_channels) for n in ph["widths"]}
            nets[ph["name"]] = prune_network(parent, ph["widths"], scores)
            continue
        cfg = rcp.phase_train_config(r, ph)
        net = FrustumShapeNet(cfg.model_config())
        if ph.get("init"):
            load_init(net, nets[ph["init"]], cfg.reinit)
        if cfg.trainable:
            assert freeze(net, cfg.trainable), ph["name"]
        if cfg.teacher in nets:  # a phase as the teacher: its heads are the ones this phase trains
            for key in ("num_classes", "num_heading_bins", "num_size_clusters"):
                assert getattr(nets[cfg.teacher].config, key) == getattr(net.config, key), ph["name"]
        elif cfg.teacher:
            from shape_detector.training.train import load_teacher

            load_teacher(cfg, net, torch.device("cpu"))
        nets[ph["name"]] = net
    # the exported network is the shipped architecture at `width`
    from shape_detector.model.config import ModelConfig

    final = rcp.phase_train_config(r, rcp.phase(r, r["exports"]["default.pt"])).model_config().to_dict()
    if width is None:  # pruned: the exported phase trains the pruned network it starts from
        assert nets[r["exports"]["default.pt"]].config.to_dict() == final
        return
    shipped = ModelConfig().to_dict()
    for k, v in shipped.items():
        if k.endswith(("widths", "_fc")):
            assert final[k] == [int(w * width) for w in v], k
        else:
            assert final[k] == v, k


@pytest.mark.slow
def test_prune_and_distil_phases_run_after_an_adopted_phase(tmp_path, capsys):
    """A prune phase narrows an earlier phase's network and a distilled phase fine-tunes it with
    that earlier phase as the teacher; both run in a directory where the earlier phase was
    only adopted from its weights file, and their keys hold the teacher's sha256."""
    from shape_detector.model.io import load_weights
    from shape_detector.training.runner import adopt, run_recipe

    child = json.loads(TINY.read_text())
    child["inherits"] = str(TINY.parent / child["inherits"])
    widths = {"seg_widths": [16, 16, 24], "box_widths": [16, 24]}
    child["exports"] = {"default.pt": "distil"}
    child["phases"] = [
        child["phases"][0],
        {"name": "prune", "kind": "prune", "network": "fresh", "score_data": ["gt_val", "gt_train"], "frustums": 20,
         "widths": {"seg_mlp": 24, "box_mlp": 24}},
        {"name": "distil", "init": "prune", "train_data": ["gt_train"], "val_data": "gt_val", "seed": 2,
         "train": {"epochs": 1, "teacher": "fresh", "model": widths,
                   "loss_weights": {"distill_seg": 1.0, "distill_box": 1.0, "distill_cls": 0.5}}},
    ]
    r = rcp.load_recipe(_write(tmp_path / "pruned.json", child))
    data = tmp_path / "data"
    run_recipe(r, tmp_path / "a", data, only=["fresh"], say=lambda s: None)
    fresh = tmp_path / "a" / "fresh" / json.loads((tmp_path / "a" / "fresh" / "result.json").read_text())["file"]

    out = tmp_path / "b"
    assert adopt(r, out, [fresh], say=lambda s: None) == ["fresh"]
    assert adopt(r, out, [fresh], say=lambda s: None) == []  # a phase with a result is left alone
    said: list[str] = []
    run_recipe(r, out, data, only=["prune", "distil"], say=said.append)
    pruned, meta = load_weights(out / "prune" / "pruned.pt")
    assert tuple(pruned.config.seg_widths) == (16, 16, 24) and tuple(pruned.config.box_widths) == (16, 24)
    assert meta["pruned_from"]["sha256"] == sha256_file(fresh) and meta["provenance"]["phase"] == "prune"
    res = json.loads((out / "distil" / "result.json").read_text())
    net, dmeta = load_weights(out / "distil" / res["file"])
    assert tuple(net.config.seg_widths) == (16, 16, 24)
    assert dmeta["teacher"]["sha256"] == sha256_file(fresh)
    assert {p["phase"] for p in dmeta["provenance"]["parents"]} == {"prune", "fresh"}
    said = []
    run_recipe(r, out, data, only=["prune", "distil"], say=said.append)
    assert sum("skipped" in s for s in said) == 2, said

    # only weights the runner wrote for a phase of this recipe are adopted
    other = json.loads(TINY.read_text())
    other["inherits"] = child["inherits"]
    with pytest.raises(ValueError, match="provenance"):
        adopt(rcp.load_recipe(_write(tmp_path / "other.json", other)), tmp_path / "c", [fresh])
    with pytest.raises(ValueError, match="provenance"):
        adopt(r, tmp_path / "c", [WEIGHTS / "classifier.pt"])


@pytest.mark.parametrize("phase, message", [
    ({"name": "p", "kind": "prune", "network": "x", "score_data": ["gt"], "widths": {"seg_mlp": 8}}, "earlier phase"),
    ({"name": "p", "kind": "prune", "network": "a", "score_data": ["gt"], "widths": {"seg": 8}}, "width seg"),
    ({"name": "p", "kind": "prune", "network": "a", "score_data": ["gt"], "widths": {"seg_mlp": 0}}, "positive"),
    ({"name": "p", "kind": "prune", "network": "a", "widths": {"seg_mlp": 8}}, "no score_data"),
    ({"name": "p", "kind": "prune", "network": "a", "score_data": ["nope"], "widths": {"seg_mlp": 8}}, "not a known frustum"),
    ({"name": "p", "train_data": ["gt"], "train": {"teacher": "q"}}, "teacher 'q' is not an earlier phase"),
])
def test_bad_prune_and_teacher_phases_are_refused(tmp_path, phase, message):
    phases = [{"name": "a", "train_data": ["gt"]}, phase, {"name": "q", "train_data": ["gt"]}]
    p = _write(tmp_path / "r.json", {"datasets": {"train": {"seed": 1, "frames": 2}},
                                     "frustums": {"gt": {"dataset": "train"}}, "phases": phases})
    with pytest.raises(ValueError, match=message):
        rcp.load_recipe(p)
