"""``shape-detector synth ...`` subcommands end to end (tiny sizes)."""

from __future__ import annotations

from shape_detector.cli import main
from shape_detector.synth.dataset import count_frames


def test_cli_dataset_and_bag(tmp_path, capsys):
    assert main(["synth", "dataset", "--out", str(tmp_path / "ds"), "--frames", "3", "--seed", "1", "--workers", "1",
                 "--width", "96", "--height", "72", "--frames-per-shard", "2"]) == 0
    assert count_frames(tmp_path / "ds") == 3
    assert main(["synth", "bag", "--out", str(tmp_path / "bag"), "--frames", "2", "--seed", "3",
                 "--width", "96", "--height", "72"]) == 0
    assert (tmp_path / "bag" / "metadata.yaml").is_file() and (tmp_path / "bag" / "gt.json").is_file()
    out = capsys.readouterr().out
    assert "frames/s" in out and "MB" in out


def test_cli_figure(tmp_path):
    import cv2

    from shape_detector.synth.cli import configure_parser
    from shape_detector.synth.figure import write_figure

    import argparse

    p = argparse.ArgumentParser()
    configure_parser(p)
    args = p.parse_args(["figure", "--out", str(tmp_path / "g.png"), "--seed", "1", "--rows", "1", "--cols", "1"])
    assert args.synth_cmd == "figure"
    path = write_figure(tmp_path / "g.png", seed=1, rows=1, cols=1)
    img = cv2.imread(str(path))
    assert img is not None and img.shape[1] == 640
