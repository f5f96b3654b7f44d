"""``shape-detector synth``: dataset shards, the sample bag, walk-through bags, the README figure, a benchmark."""

from __future__ import annotations

import argparse


def configure_parser(p: argparse.ArgumentParser) -> None:
    """Subcommands dataset, bag, walkthrough, figure, bench."""
    sub = p.add_subparsers(dest="synth_cmd", required=True)
    d = sub.add_parser("dataset", help="generate training shards (multiprocessing)")
    d.add_argument("--out", required=True, help="output directory")
    d.add_argument("--frames", type=int, default=1000)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--workers", type=int, default=2)
    d.add_argument("--frames-per-shard", type=int, default=256)
    d.add_argument("--width", type=int, default=640)
    d.add_argument("--height", type=int, default=480)
    d.add_argument("--no-noise", action="store_true", help="store clean depth")
    d.add_argument("--rgb-format", choices=("png", "jpg"), default="png", help="png is lossless, jpg ~4x smaller")
    b = sub.add_parser("bag", help="write a rosbag2 MCAP of one generated room + gt.json")
    b.add_argument("--out", required=True, help="output bag directory (replaced if it exists)")
    b.add_argument("--frames", type=int, default=12)
    b.add_argument("--seed", type=int, default=7)
    b.add_argument("--rate", type=float, default=5.0, help="frame rate (Hz)")
    b.add_argument("--width", type=int, default=320, help="default 320x240 keeps the 12-frame sample bag < 5 MB")
    b.add_argument("--height", type=int, default=240)
    b.add_argument("--no-compress", action="store_true", help="no zstd chunk compression")
    w = sub.add_parser("walkthrough", help="write a walk-through bag: a camera moving through one room, with "
                       "/tf, /tf_static, /odom, gt.json and world-frame gt_world.json")
    w.add_argument("--out", required=True, help="output bag directory (replaced if it exists)")
    w.add_argument("--frames", type=int, default=40)
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("--rate", type=float, default=5.0, help="frame rate (Hz)")
    w.add_argument("--width", type=int, default=320)
    w.add_argument("--height", type=int, default=240)
    w.add_argument("--no-compress", action="store_true", help="no zstd chunk compression")
    f = sub.add_parser("figure", help="README figure: grid of RGB | depth frames with GT boxes")
    f.add_argument("--out", required=True)
    f.add_argument("--seed", type=int, default=3)
    f.add_argument("--rows", type=int, default=4)
    f.add_argument("--cols", type=int, default=2)
    n = sub.add_parser("bench", help="frames/s of the generator")
    n.add_argument("--frames", type=int, default=20)


def main(args: argparse.Namespace) -> int:
    """Run the chosen subcommand; exit status."""
    if args.synth_cmd == "dataset":
        from .dataset import write_shards
        from .generate import SynthConfig

        cfg = SynthConfig(width=args.width, height=args.height, noise=not args.no_noise)
        write_shards(args.out, args.frames, args.seed, frames_per_shard=args.frames_per_shard, workers=args.workers,
                     config=cfg, rgb_format=args.rgb_format)
        return 0
    if args.synth_cmd == "bag":
        from .bag import write_sample_bag

        out = write_sample_bag(args.out, args.frames, args.seed, args.rate, args.width, args.height,
                               overwrite=True, compress=not args.no_compress)
        size = sum(p.stat().st_size for p in out.iterdir())
        print(f"wrote {out} ({args.frames} frames {args.width}x{args.height} at {args.rate:g} Hz, {size / 1e6:.2f} MB)")
        return 0
    if args.synth_cmd == "walkthrough":
        from .walkthrough_bag import write_walkthrough_bag

        if args.frames < 1 or args.rate <= 0 or args.width < 16 or args.height < 16:
            print("synth walkthrough: --frames >= 1, --rate > 0 and --width/--height >= 16 needed")
            return 2
        out = write_walkthrough_bag(args.out, args.frames, args.seed, args.rate, args.width, args.height,
                                    overwrite=True, compress=not args.no_compress)
        size = sum(p.stat().st_size for p in out.iterdir())
        print(f"wrote {out} ({args.frames} frames {args.width}x{args.height} at {args.rate:g} Hz, {size / 1e6:.2f} MB)")
        return 0
    if args.synth_cmd == "figure":
        from .figure import write_figure

        print(f"wrote {write_figure(args.out, args.seed, args.rows, args.cols)}")
        return 0
    if args.synth_cmd == "bench":
        from .bench import bench_synth

        bench_synth(frames=args.frames)
        return 0
    return 2
