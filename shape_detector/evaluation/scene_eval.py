"""Scene-map evaluation on generated walk-through sequences (world frame, z up, metres).

For each walk-through (:func:`shape_detector.synth.walkthrough.walkthrough`) the detector
runs on every frame and a :class:`~shape_detector.scene.SceneMap` is fed its objects with
the **true** camera poses, or with poses that drift and jitter as odometry's would
(:mod:`.pose_noise`; the metrics stay against the true world). Against the world-frame ground truth of the objects *seen* in
at least ``min_frames`` frames (:func:`seen_frames`: enough pixels, not mostly hidden):

* ``map_mAP`` -- mAP@0.25 / @0.5 of the final map (one "frame" per sequence; the
  evaluation of :mod:`.ap` with :mod:`shape_detector.box_iou`);
* ``stack_mAP`` -- the baseline: every frame's detections moved to the world and stacked;
* ``map_mAP_runner_up`` -- for comparison only: the final map with each object also scored
  for its runner-up class (score times the class's share of the top class's probability), the
  per-class protocol VoteNet and others use on SUN RGB-D;
* ``duplicates_per_object`` -- final tracks beyond the first whose best 3D IoU (any class,
  >= 0.25) is with the same object, per object;
* ``id_switches_per_object`` -- changes of the published track id best matching an object
  (IoU >= 0.25) from frame to frame, per object;
* ``jitter_cm`` -- per object, the RMS distance of its track's published centre to that
  track's mean centre over the frames after confirmation (the object's most frequent id),
  averaged over objects;
* ``grid_iou`` -- IoU of the map grid's occupied cells and the cells the objects' true
  parts occupy by the same rule (:func:`shape_detector.scene.grid.build_grid`);
* ``object_iou`` -- per object, the 3D IoU of its best same-class final track (0 when none):
  the median and the shares at >= 0.25 / 0.5. The mAP is a mean over classes of which some
  have two or three objects in all, so one object crossing 0.5 moves it by several points;
  these per-object numbers show whether a change moved many objects or one.

Objects glimpsed but seen in fewer frames are *ignored* (like the AP's difficult objects):
a track on one is neither a hit nor a false positive, and their cells are left out of the
grid IoU. Objects never in view are not part of the ground truth at all.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..box_iou import iou_matrix
from ..types import GTObject, Object3D
from .ap import evaluate_detections


@dataclass
class SequenceData:
    """One walk-through with the detector's output: per frame the objects (camera frame),
    the pose, depth, K and stamp; the world GT and how many frames saw each object."""

    seed: int
    detections: list[list[Object3D]]
    poses: list[np.ndarray]
    depths: list[np.ndarray]
    Ks: list[np.ndarray]
    stamps: list[int]
    gt_world: list[GTObject]
    #: (frames, objects) pixels of each object in each frame's instance mask
    pixels: np.ndarray
    #: (frames, objects) visible fraction (occlusion and truncation) of each object, 0 when out of view
    visible: np.ndarray
    detect_ms: list[float] = field(default_factory=list)


def collect(seeds: Sequence[int], frames: int, width: int = 640, height: int = 480,
            detector: Any = None, progress: Callable[[str], None] | None = None,
            up: str = "pose", pose_noise: Any = None, config: Any = None, processes: int = 1,
            gt_2d: str | None = None) -> list[SequenceData]:
    """Render each walk-through and run the detector on it (:func:`collect_one`), in seed
    order; ``up``, ``pose_noise``, ``gt_2d``: as there. The detector: ``detector``, else one built from
    ``config`` (a ``DetectorConfig``; None: the defaults); with ``processes`` > 1 and no
    ``detector``, that many worker processes each build their own (:func:`~.parallel.map_seeds`)."""
    from .parallel import map_seeds

    if up not in ("pose", "estimate"):
        raise ValueError(f"up must be 'pose' or 'estimate', got {up!r}")
    if config is None and detector is None:
        from ..detector_config import preset

        config = preset("realtime")
    kw = dict(frames=frames, width=width, height=height, up=up, pose_noise=pose_noise, gt_2d=gt_2d)
    out = []
    for d in map_seeds(collect_one, seeds, config, 1 if detector is not None else processes, detector, **kw):
        out.append(d)
        if progress:
            progress(f"sequence {d.seed}: {len(d.detections)} frames, {len(d.gt_world)} objects, "
                     f"detector {np.mean(d.detect_ms):.0f} ms/frame")
    return out


def collect_one(seed: int, frames: int, width: int = 640, height: int = 480, detector: Any = None,
                up: str = "pose", pose_noise: Any = None, gt_2d: str | None = None) -> SequenceData:
    """Render walk-through ``seed`` and run ``detector`` on each frame. ``up``: the gravity
    the detector gets, ``pose`` (the reported pose's z axis, as the node's ``up_source:
    auto`` gives it) or ``estimate`` (the detector estimates it per frame). ``pose_noise``:
    a :class:`~.pose_noise.PoseNoise` applied to the poses the map (and the detector's
    gravity) gets, seeded by the sequence; None: the true poses. ``gt_2d``: the frames' true
    2D boxes instead of the detector's proposals (:func:`~.runner.detect_walkthrough_frame`)."""
    from ..synth.generate import SynthConfig
    from ..synth.walkthrough import walkthrough
    from ..poses import camera_up
    from .pose_noise import PoseNoise, noisy_poses
    from .runner import detect_walkthrough_frame

    wt = walkthrough(int(seed), frames, config=SynthConfig(width=width, height=height))
    poses = noisy_poses(wt.poses, pose_noise or PoseNoise(), seed=int(seed))
    dets, ms = [], []
    n = len(wt.gt_world)
    pixels = np.stack([_visible(f, n) for f in wt.frames]) if wt.frames else np.zeros((0, n))
    visible = np.zeros((len(wt.frames), n))
    for i, f in enumerate(wt.frames):
        for g in f.objects:
            if 1 <= g.instance_id <= n:
                visible[i, g.instance_id - 1] = g.visible_fraction
    for f, T in zip(wt.frames, poses):
        t0 = time.perf_counter()
        g = camera_up(T) if up == "pose" else None
        dets.append(detect_walkthrough_frame(detector, f, g, gt_2d))
        ms.append(1000.0 * (time.perf_counter() - t0))
    return SequenceData(int(seed), dets, poses, [f.depth for f in wt.frames], [f.K for f in wt.frames],
                        [int(f.stamp_ns) for f in wt.frames], wt.gt_world, pixels, visible, ms)


def _visible(frame: Any, n: int) -> np.ndarray:
    """(n,) pixel counts of instances 1..n in the frame's instance mask."""
    if frame.instance_mask is None:
        return np.zeros(n, dtype=np.int64)
    return np.bincount(frame.instance_mask.ravel().clip(0), minlength=n + 1)[1:n + 1]


def run_map(data: SequenceData, config: Any = None) -> tuple[Any, list[list[Any]]]:
    """Feed one sequence to a fresh SceneMap; returns (the map, published objects per frame)."""
    from ..scene import SceneMap

    m = SceneMap(config)
    per_frame = []
    m.update_seconds = 0.0  # type: ignore[attr-defined]
    for objs, T, d, K, s in zip(data.detections, data.poses, data.depths, data.Ks, data.stamps):
        t0 = time.perf_counter()
        m.update(objs, T, d, K, s)
        m.update_seconds += time.perf_counter() - t0  # type: ignore[attr-defined]
        per_frame.append(m.objects())
    return m, per_frame


def _world_dets(data: SequenceData) -> list[Object3D]:
    out = []
    for objs, T in zip(data.detections, data.poses):
        for o in objs:
            R, t = T[:3, :3], T[:3, 3]
            out.append(Object3D(o.class_name, o.score, R @ o.center + t, o.size, R @ o.rotation))
    return out


def best_gt(objs: Sequence[Any], gts: Sequence[GTObject], thr: float = 0.25) -> list[int]:
    """Per object the index of its best-overlapping GT (3D IoU >= thr, any class) or -1."""
    if not objs or not gts:
        return [-1] * len(objs)
    m = iou_matrix(objs, gts)
    return [int(np.argmax(r)) if r.max() >= thr else -1 for r in m]


def _same_class_iou(objs: Sequence[Any], gts: Sequence[GTObject]) -> list[float]:
    """Per GT object the 3D IoU of its best-overlapping object of the same class (0 when none)."""
    if not gts:
        return []
    if not objs:
        return [0.0] * len(gts)
    m = iou_matrix(objs, gts)
    same = np.array([[o.class_name == g.class_name for g in gts] for o in objs])
    return np.where(same, m, 0.0).max(axis=0).tolist()


def _tracking_metrics(per_frame: list[list[Any]], gts: list[GTObject]) -> tuple[int, list[float], int]:
    """(identity switches, per-object jitter in cm, objects tracked)."""
    ids: list[list[int]] = [[] for _ in gts]
    centres: list[dict[int, list[np.ndarray]]] = [{} for _ in gts]
    for objs in per_frame:
        best = best_gt(objs, gts)
        cand: dict[int, tuple[float, Any]] = {}
        for o, g in zip(objs, best):
            if g >= 0:
                iou = float(iou_matrix([o], [gts[g]])[0, 0])
                if g not in cand or iou > cand[g][0]:
                    cand[g] = (iou, o)
        for g, (_, o) in cand.items():
            ids[g].append(o.id)
            centres[g].setdefault(o.id, []).append(np.asarray(o.center))
    switches = sum(sum(1 for a, b in zip(seq, seq[1:]) if a != b) for seq in ids)
    jitter = []
    for g, seq in enumerate(ids):
        if not seq:
            continue
        main = max(set(seq), key=seq.count)
        c = np.stack(centres[g][main])
        if len(c) >= 2:
            jitter.append(100.0 * float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1)))))
    return switches, jitter, sum(1 for s in ids if s)


def _occupied_cells(grid: Any) -> set[tuple[int, int]]:
    """World cell indices (row, col) of a grid's occupied cells."""
    r0 = int(round(grid.origin[1] / grid.resolution))
    c0 = int(round(grid.origin[0] / grid.resolution))
    rows, cols = np.nonzero(grid.data == 100)
    return set(zip((rows + r0).tolist(), (cols + c0).tolist()))


def grid_iou(grid: Any, gts: Sequence[GTObject], agent_height: float = 1.8, min_height: float = 0.05,
             ignored: Sequence[GTObject] = ()) -> float:
    """IoU of ``grid``'s occupied cells and those the GT parts occupy (floor at z = 0); the
    cells under ``ignored`` objects (glimpsed too briefly to count) are left out of both."""
    from ..scene.grid import FloorMemory, build_grid

    def cells(objs: Sequence[GTObject]) -> set[tuple[int, int]]:
        parts = [(p.center, p.size, p.rotation) for g in objs for p in (g.parts or [g.cuboid])]
        return _occupied_cells(build_grid(FloorMemory(grid.resolution), parts, 0.0, agent_height, min_height))

    a, b = _occupied_cells(grid), cells(gts)
    skip = cells(ignored) - b if ignored else set()
    a, b = a - skip, b - skip
    return len(a & b) / len(a | b) if (a | b) else float("nan")


def with_runner_up(objects: Sequence[Any]) -> list[Any]:
    """Each scene object, plus a copy labelled with its runner-up class (from
    ``class_probs``) scored ``score * p2 / p1``; objects without a runner-up pass as they are."""
    out: list[Any] = []
    for o in objects:
        out.append(o)
        ranked = sorted(getattr(o, "class_probs", {}).items(), key=lambda kv: -kv[1])
        if len(ranked) >= 2 and ranked[0][1] > 0:
            out.append(replace(o, class_name=ranked[1][0], score=o.score * ranked[1][1] / ranked[0][1]))
    return out


def seen_frames(data: SequenceData, min_pixels: int = 1000, min_visible: float = 0.25) -> np.ndarray:
    """(objects,) number of frames in which each object is *seen*: at least ``min_pixels``
    pixels (at 640 x 480; scaled with the image area) and at least ``min_visible`` of it
    neither occluded nor cut by the image border."""
    h, w = data.depths[0].shape if data.depths else (480, 640)
    px = min_pixels * (h * w) / (640.0 * 480.0)
    return ((data.pixels >= px) & (data.visible >= min_visible)).sum(axis=0)


def labelled_objects(data: SequenceData, min_frames: int = 3, min_pixels: int = 1000,
                     min_visible: float = 0.25) -> tuple[list[GTObject], list[GTObject]]:
    """(ground truth, ignored) of one walk-through: the objects seen (:func:`seen_frames`) in at
    least ``min_frames`` frames, and those glimpsed (some pixels in some frame) in fewer."""
    seen = seen_frames(data, min_pixels, min_visible)
    glimpsed = data.pixels.sum(axis=0) > 0
    gts = [g for g, n in zip(data.gt_world, seen) if n >= min_frames]
    ignored = [g for g, n, v in zip(data.gt_world, seen, glimpsed) if n < min_frames and v]
    return gts, ignored


def score_sequences(data: Sequence[SequenceData], config: Any = None, min_frames: int = 3,
                    min_pixels: int = 1000, min_visible: float = 0.25) -> dict[str, Any]:
    """The metrics of the module docstring over ``data`` (one SceneMap per sequence); the
    ground truth are the objects seen (:func:`seen_frames`) in at least ``min_frames`` frames;
    objects seen in fewer (but glimpsed: some pixels in some frame) are *ignored*, as the
    AP's difficult objects: a track on one is neither a hit nor a false positive, and their
    cells are left out of the grid IoU."""
    finals, stacks, gts_all, ignore_all = [], [], [], []
    n_obj = switches = dups = 0
    jitter: list[float] = []
    giou: list[float] = []
    update_ms: list[float] = []
    best_iou: list[float] = []
    for d in data:
        gts, ignored = labelled_objects(d, min_frames, min_pixels, min_visible)
        m, per_frame = run_map(d, config)
        update_ms.append(1000.0 * m.update_seconds / max(len(d.detections), 1))  # type: ignore[attr-defined]
        final = m.objects()
        finals.append(final)
        stacks.append(_world_dets(d))
        gts_all.append(gts + ignored)
        ignore_all.append([False] * len(gts) + [True] * len(ignored))
        n_obj += len(gts)
        best_iou += _same_class_iou(final, gts)
        best = [b for b in best_gt(final, gts) if b >= 0]
        dups += sum(max(0, best.count(g) - 1) for g in set(best))
        s, j, _ = _tracking_metrics(per_frame, gts)
        switches += s
        jitter += j
        giou.append(grid_iou(m.grid(), gts, m.config.agent_height, m.config.min_obstacle_height, ignored))
    fin = evaluate_detections(finals, gts_all, ignore_per_frame=ignore_all)
    hyp = evaluate_detections([with_runner_up(f) for f in finals], gts_all, ignore_per_frame=ignore_all)
    stk = evaluate_detections(stacks, gts_all, ignore_per_frame=ignore_all)
    return {
        "sequences": len(data), "objects": n_obj,
        "map_mAP": {k: 100.0 * v for k, v in fin["mAP"].items()},
        "stack_mAP": {k: 100.0 * v for k, v in stk["mAP"].items()},
        "map_mAP_runner_up": {k: 100.0 * v for k, v in hyp["mAP"].items()},
        "map_ap_per_class": {k: {c: 100.0 * v for c, v in a.items() if fin["num_gt"][c] > 0}
                             for k, a in fin["ap"].items()},
        "tracks": sum(len(f) for f in finals),
        "duplicates_per_object": dups / max(n_obj, 1),
        "id_switches_per_object": switches / max(n_obj, 1),
        "jitter_cm": float(np.mean(jitter)) if jitter else float("nan"),
        "grid_iou": float(np.nanmean(giou)) if np.isfinite(giou).any() else float("nan"),
        "object_iou": {"median": float(np.median(best_iou)) if best_iou else float("nan"),
                       **{k: float(np.mean(np.asarray(best_iou) >= float(k))) if best_iou else float("nan")
                          for k in ("0.25", "0.5")}},
        "map_update_ms": float(np.mean(update_ms)) if update_ms else float("nan"),
        "detector_ms": float(np.mean(ms)) if (ms := [x for d in data for x in d.detect_ms]) else float("nan"),
    }

