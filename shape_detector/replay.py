"""``shape-detector replay``: run the detector over a recorded bag, or play a bag live.

Offline (``shape-detector replay IN -o OUT``): every synchronised frame of ``IN`` goes
through the detector (nothing is dropped offline) and ``OUT`` - a rosbag2 MCAP - gets the
input topics plus ``/shape_detector/markers`` (and ``/shape_detector/detections``) at the
input stamps; with ``--scene-out scene.json`` (or ``--world-frame``) also the scene map
(``/shape_detector/scene``, ``/shape_detector/map``) with camera poses from ``/tf``,
``--odom-topic`` or ``--pose-topic``. Library use::

    from shape_detector.replay import replay_bag
    summary = replay_bag("bags/sample", "out/sample_detections", detector)
    print(summary.format())

Live (``shape-detector replay IN --play``): publishes the bag's topics with rclpy at real
or scaled rate (``--rate``), optionally re-stamped to the current time (``--restamp``).

This module is the command line; the work is done in :mod:`shape_detector.bags`
(``offline``, ``player``, ``detector_factory``, ``scene_record``).
"""

from __future__ import annotations

import argparse
import sys

from .bags.detector_factory import factory_kwargs, load_factory, make_detector
from .bags.offline import replay_bag
from .bags.player import PlaySummary, play_bag
from .bags.scene_record import SceneOptions
from .bags.source import DETECTIONS_TOPIC, MAP_TOPIC, MARKERS_TOPIC, SCENE_TOPIC, BagReadError
from .bags.summary import ReplaySummary
from .config_cli import add_detector_flags, add_setting_flags
from .detector_config import PROPOSAL_SOURCES
from .node_params import NodeConfig
from .settings import specs

#: the scene map's settings, shared with the node (its parameters of these names)
SCENE_SETTINGS = ("grid_resolution", "inflation_radius", "scene_confirm_observations", "scene_delete_misses",
                  "scene_publish_score", "scene_track_classifier", "scene_in")


def _check_device_flag(p: argparse.ArgumentParser) -> None:
    """``--device`` refuses what is not a device name at parse time (the setting itself is free text)."""
    from .bags import cli_args as ca

    for action in p._actions:  # argparse has no public way to reach an added flag
        if action.dest == "device":
            action.type = ca.device


def scene_options(args: argparse.Namespace) -> SceneOptions | None:
    """The scene the flags ask for; None when none of ``--scene-out``, ``--scene-in``,
    ``--world-frame``, ``--odom-topic``, ``--pose-topic`` is given."""
    if not (args.scene_out or args.scene_in or args.world_frame or args.odom_topic or args.pose_topic):
        return None
    from .node_scene import scene_config

    return SceneOptions(world_frame=args.world_frame or "odom", scene_out=args.scene_out, scene_in=args.scene_in or None,
                        odom_topic=args.odom_topic, pose_topic=args.pose_topic,
                        config=scene_config({**{k: getattr(args, k) for k in SCENE_SETTINGS}, "world_frame": "odom"}))


def configure_parser(p: argparse.ArgumentParser) -> None:
    """The flags of ``shape-detector replay`` (detector settings from the realtime preset)."""
    from .bags import cli_args as ca
    from .bags.replay_cli import EXIT_STATUS_HELP

    p.description = (
        "Run the detector over a bag (rosbag2 MCAP/sqlite3 directory or file, ROS 1 .bag) and write "
        "a rosbag2 MCAP with the input topics plus /shape_detector/markers and /shape_detector/detections "
        "(and, with --scene-out / --world-frame, /shape_detector/scene and /shape_detector/map); or, with "
        "--play, publish the bag live."
    )
    p.epilog = EXIT_STATUS_HELP
    p.add_argument("bag", type=ca.path_text, help="input bag: rosbag2 directory, .mcap, .db3 or ROS 1 .bag")
    p.add_argument("-o", "--out", type=ca.path_text,
                   help="output rosbag2 directory (MCAP); required unless --play; must not be, contain or lie "
                        "inside the input")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output bag (only once the new one is complete)")
    g = p.add_argument_group("topics (default: chosen automatically)")
    g.add_argument("--image", type=ca.topic, help="colour sensor_msgs/Image topic")
    g.add_argument("--depth", type=ca.topic, help="depth sensor_msgs/Image topic (16UC1 / 32FC1, registered to colour)")
    g.add_argument("--camera-info", dest="camera_info", type=ca.topic, help="colour sensor_msgs/CameraInfo topic")
    g.add_argument("--imu", type=ca.topic,
                   help="sensor_msgs/Imu topic for gravity-up (IMU in the camera optical frame)")
    g.add_argument("--detections2d", type=ca.topic,
                   help="vision_msgs/Detection2DArray topic with external 2D proposals")
    add_detector_flags(p, "realtime")
    _check_device_flag(p)
    d = p.add_argument_group("detector source")
    d.add_argument("--proposals", choices=PROPOSAL_SOURCES, default=None,
                   help="same as --proposal-source (default: external when --detections2d is given)")
    d.add_argument("--detector", metavar="MODULE:CALLABLE", help="use another detector factory (tests, plugins)")
    d.add_argument("--processes", type=ca.int_at_least(0), default=0, metavar="N",
                   help="run the detector in N worker processes, frames in flight in parallel while the bag "
                        "is read and written (output in input order; about 150 MiB each; 0 = in this process)")
    sc = p.add_argument_group("scene (tracked objects in a fixed frame and a navigation grid)")
    sc.add_argument("--scene-out", type=ca.path_text, default=None, metavar="JSON",
                    help="build the scene map, write /shape_detector/scene and /shape_detector/map per frame "
                         "and the final map to this JSON file")
    sc.add_argument("--world-frame", type=ca.topic, default=None,
                    help="fixed frame of the scene (default odom); giving it turns the scene on")
    add_setting_flags(sc, specs(NodeConfig), SCENE_SETTINGS)
    pose = sc.add_mutually_exclusive_group()
    pose.add_argument("--odom-topic", type=ca.topic, default=None,
                      help="camera pose from this nav_msgs/Odometry topic (default: /tf + /tf_static)")
    pose.add_argument("--pose-topic", type=ca.topic, default=None,
                      help="camera pose from this geometry_msgs/PoseStamped topic")
    s = p.add_argument_group("frames")
    s.add_argument("--slop", type=ca.seconds, default=0.02, help="synchroniser slop, seconds >= 0 (default 0.02)")
    s.add_argument("--queue-size", type=ca.int_at_least(1), default=30,
                   help="synchroniser queue size per topic, >= 1 (default 30)")
    s.add_argument("--depth-scale", type=ca.depth_scale, default=None,
                   help="metres per raw depth unit, > 0 (default: by encoding, 16UC1 = 0.001)")
    s.add_argument("--up", type=ca.up_vector,
                   help="fixed gravity-up vector in the camera optical frame, e.g. 0,-1,0 (default: the IMU's with "
                        "--imu, else with the scene on the camera pose's (world z up), else estimated per frame)")
    s.add_argument("--size-mismatch", choices=("rescale", "skip"), default="rescale")
    s.add_argument("--no-detections", action="store_true", help="do not write the Detection3DArray topic")
    s.add_argument("--no-copy", action="store_true", help="write only the detector's topics, not the input")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    pl = p.add_argument_group("live playback (--play)")
    pl.add_argument("--play", action="store_true", help="publish the bag's topics live instead")
    pl.add_argument("--rate", type=ca.rate, default=1.0, help="playback rate factor (<= 0: as fast as possible)")
    pl.add_argument("--topics", nargs="+", type=ca.topic, help="publish only these topics")
    pl.add_argument("--remap", nargs="+", type=ca.remap, default=[], metavar="FROM:=TO",
                    help="publish topic FROM as TO")
    pl.add_argument("--restamp", action="store_true", help="map header stamps to wall-clock time")
    pl.add_argument("--loop", action="store_true", help="play again and again")
    pl.add_argument("--clock", action="store_true", help="also publish /clock")
    pl.add_argument("--wait-subscribers", type=ca.seconds, default=0.0, metavar="SEC",
                    help="wait up to SEC (>= 0) seconds for subscribers before playing (all topics, or some "
                         "and no new ones for 1 s)")
    pl.add_argument("--delay", type=ca.seconds, default=0.0, help="seconds (>= 0) to wait before playing")


def _main_play(args: argparse.Namespace) -> int:
    """``--play``: publish the bag live; exit status 0, 1 or 130."""
    remap = dict(args.remap)
    import rclpy

    rclpy.init()
    try:
        summary = play_bag(
            args.bag, args.rate, topics=args.topics, remap=remap, restamp=args.restamp, loop=args.loop,
            clock=args.clock, wait_subscribers=args.wait_subscribers, start_delay=args.delay,
            log=lambda s: print(s, file=sys.stderr),
        )
    except KeyboardInterrupt:
        return 130
    except (FileNotFoundError, ValueError, BagReadError) as e:
        print(f"replay --play: {e}", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - e.g. the context shut down by Ctrl-C mid-publish
        if not rclpy.ok():
            return 130
        print(f"replay --play: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        rclpy.try_shutdown()
    per = ", ".join(f"{t} {n}" for t, n in sorted(summary.per_topic.items()))
    print(f"played {summary.published} messages in {summary.wall_s:.2f} s ({per})")
    if summary.error:
        print(f"replay --play: {summary.error}", file=sys.stderr)
        return 1
    return 0


def main(args: argparse.Namespace) -> int:
    """Exit status: see :mod:`shape_detector.bags.replay_cli` (0, 1, 2, 3, 130, 143)."""
    if args.play:
        return _main_play(args)
    if not args.out:
        print("shape-detector replay: -o/--out OUT is required (or use --play)", file=sys.stderr)
        return 2
    from .bags.replay_cli import run_offline

    return run_offline(args, make_detector, replay_bag)


__all__ = [
    "DETECTIONS_TOPIC",
    "MAP_TOPIC",
    "MARKERS_TOPIC",
    "SCENE_TOPIC",
    "PlaySummary",
    "ReplaySummary",
    "configure_parser",
    "factory_kwargs",
    "load_factory",
    "main",
    "make_detector",
    "play_bag",
    "replay_bag",
    "scene_options",
]
