"""SceneMap: tracked furniture in a fixed world frame and a navigation grid (pure numpy).

World frame: z up, metres; stamps int ns. Each :meth:`SceneMap.update` takes the detector's
objects (camera optical frame: x right, y down, z forward), the pose ``T_world_camera``
(4x4, camera optical frame -> world) and the frame's depth (metres) and intrinsics:

1. detections become world-frame observations (:mod:`.observe`), weighted by score x the
   share of the box inside the image;
2. they are assigned to tracks in 3D (:mod:`.association`: centre distance in units of the
   footprint, height, and a class term that a one-frame class flip cannot outweigh);
   matched tracks fuse them (:mod:`.tracks`), unmatched ones start tentative tracks unless
   they overlap a track already matched this frame (a second box on one object);
3. tracks not matched whose space the depth shows empty lose support (:mod:`.visibility`)
   and are removed after ``delete_misses`` such frames; out-of-view or hidden tracks stay;
   tentative tracks not seen again within ``tentative_max_age`` frames are dropped;
4. overlapping tracks merge (the older id stays); a weak track overlapping a far stronger one
   of its class in part is a displaced duplicate and dropped;
5. the floor seen in the depth is added to the grid (:mod:`.grid`), and the depth points
   above it to the observed surfaces (:mod:`.surface`), which ray casts land on;
6. the track classifier (:mod:`.track_classifier`) decides each published track's class and
   score from the whole track (``SceneConfig.track_classifier``).

A track is published (:meth:`objects`) once seen in ``confirm_observations`` frames.
Without a pose (static camera) the world is the camera frame turned so that z is up
(``up_camera``), origin at the camera; the map says so once (warning and log).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..classes import CLASSES
from ..types import Object3D
from .association import associate, class_similarity, cost_matrix, duplicates, overlap
from .grid import (FloorMemory, NavGrid, build_grid, depth_points_world, estimate_floor_z, floor_cells_seen,
                   floor_from_estimates)
from .json_io import grid_from_dict, load_dict, scene_to_dict, structure_from_dict, write_json
from .observe import to_observation
from .surface import SurfaceMemory, split_points
from .track_classifier import TrackClassifier, load_track_classifier, tracks_features
from .tracks import N_CLASSES, Observation, Track, track_score, tracks_state
from .types import SceneObject, ScenePrimitive
from .visibility import EmptyParams, seen_empty_many

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SceneConfig:
    """Settings of :class:`SceneMap` (metres, frames and counts of updates)."""

    #: name of the fixed world frame (z up)
    world_frame: str = "odom"
    #: navigation grid cell size
    grid_resolution: float = 0.05
    #: grid inflation for the agent's radius (:meth:`SceneMap.grid` with ``inflate=True``)
    inflation_radius: float = 0.2
    #: a track is published once detected in this many frames
    confirm_observations: int = 3
    #: ... and once its accumulated fusion weight (about the number of sure, fully visible
    #: detections) reaches this: the box has settled before it is published
    confirm_weight: float = 0.1
    #: a confirmed track is published (objects, grid, JSON) while its score is at least this:
    #: tracks that stay doubtful are mostly on clutter or second tracks of one object
    publish_score: float = 0.5
    #: a track is removed after this many frames in which its space is seen empty
    delete_misses: int = 3
    #: an unpublished track not detected for this many frames is dropped
    tentative_max_age: int = 8
    #: association gate (cost units: centre distance / mean footprint radius + terms)
    gate: float = 1.0
    #: association cost of a class the track has no evidence for
    class_weight: float = 0.4
    #: cap of a track's accumulated fusion weight (higher: steadier box, slower to adapt)
    max_weight: float = 30.0
    #: detections scored lower are ignored
    min_score: float = 0.0
    #: parts below this height above the floor block the agent (see :mod:`.grid`)
    agent_height: float = 1.8
    #: parts whose top is lower than this above the floor do not block (rugs)
    min_obstacle_height: float = 0.05
    #: world z of the floor; None estimates it from the depth (lowest dense height)
    floor_z: float | None = None
    #: depth points within this height of the floor mark free cells
    floor_band: float = 0.05
    #: every n-th depth row and column is used for the floor and the observed surfaces
    depth_stride: int = 4
    #: depth points beyond this range are not used for the floor
    max_range: float = 6.0
    #: floor within this radius of the camera's path counts as free (the camera, held by a person or
    #: carried by a robot, has passed there, though it rarely sees that floor); 0 = off
    camera_path_radius: float = 0.3
    #: observed surfaces (for ray casts) are kept as the mean depth point per cube of this size; 0 = off
    surface_voxel: float = 0.02
    #: an object's surface is the observed points inside its box grown by this much (boxes are a few
    #: centimetres off; what lies just beside them is mostly their own surface)
    surface_pad: float = 0.1
    #: ... in voxels that this many depth points fell into (stray edge pixels seldom repeat)
    surface_min_count: int = 2
    #: two tracks with a 3D IoU above this merge
    merge_iou: float = 0.4
    #: two tracks of agreeing class whose intersection over the smaller box is above this merge
    merge_ios: float = 0.6
    #: a track overlapping (3D IoU at least this) one of agreeing class with far more fusion weight
    #: (``displaced_share``) is a displaced duplicate and dropped; 0 = off
    displaced_iou: float = 0.1
    #: ... at most this share of the other's weight
    displaced_share: float = 0.3
    #: track classifier deciding published tracks' classes and scores from the whole track
    #: (:mod:`.track_classifier`): "default" (the packaged one), a weights file, or "" (off: the
    #: accumulated class evidence decides)
    track_classifier: str = "default"


def level_rotation(up_camera: np.ndarray | None) -> np.ndarray:
    """(3,3) rotation camera optical frame -> a world whose z is ``up_camera`` (camera
    frame; None: a level camera, (0, -1, 0)) and whose x is the camera's x made horizontal."""
    u = np.array([0.0, -1.0, 0.0]) if up_camera is None else np.asarray(up_camera, dtype=np.float64).reshape(3)
    u = u / max(np.linalg.norm(u), 1e-9)
    x = np.array([1.0, 0.0, 0.0]) - u * u[0]
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 0.0, 1.0]) - u * u[2]
    x = x / np.linalg.norm(x)
    y = np.cross(u, x)
    return np.stack([x, y, u])  # rows: world axes in camera coordinates


class SceneMap:
    """The scene memory (see the module docstring)."""

    def __init__(self, config: SceneConfig | None = None) -> None:
        self.config = config or SceneConfig()
        self.frame_id: str = self.config.world_frame
        self.stamp_ns: int = 0
        self.tracks: list[Track] = []
        self.floor = FloorMemory(self.config.grid_resolution)
        self._next_id = 1
        self._floor_estimates: list[float] = []
        self._floor_cache: float | None = None
        self._static_warned = False
        self._grid: NavGrid | None = None
        self._empty = EmptyParams()
        self.frames = 0
        v = self.config.surface_voxel
        self.surface: SurfaceMemory | None = SurfaceMemory(v) if v > 0 else None
        #: re-decides published tracks' classes and scores (:mod:`.track_classifier`); None: off
        self.classifier: TrackClassifier | None = load_track_classifier(self.config.track_classifier)

    # -- public --------------------------------------------------------------------
    def update(self, objects: Sequence[Object3D], T_world_camera: np.ndarray | None, depth: np.ndarray | None,
               K: np.ndarray | None, stamp_ns: int, up_camera: np.ndarray | None = None) -> None:
        """Fold one frame into the map (see the module docstring). ``objects``: detector
        output, camera optical frame; ``T_world_camera``: (4,4) or None (static camera);
        ``depth``: (H,W) metres or None; ``K``: (3,3) intrinsics of ``depth``."""
        T = self._pose(T_world_camera, up_camera)
        depth = _depth_metres(depth, K)
        self.stamp_ns = int(stamp_ns)
        self.frames += 1
        obs = self._observations(objects, T, depth, K)
        matched = self._assign(obs)
        if depth is not None:
            self._negative_evidence(matched, T, depth, np.asarray(K, np.float64))
        self._age(matched)
        self._merge()
        if depth is not None:
            self.integrate_floor(T, depth, np.asarray(K, np.float64))
        if T_world_camera is not None and self.config.camera_path_radius > 0:
            # half-cell lattice: every cell the disc covers gets a point, wherever the cell lines fall
            self.floor.add(disc_points(T[:2, 3], self.config.camera_path_radius, 0.5 * self.config.grid_resolution))
        self._decide()
        self._grid = None

    def objects(self, surfaces: bool = False) -> list[SceneObject]:
        """The confirmed tracks, sorted by id; ``surfaces``: each with the observed surface
        points inside its box (``SceneObject.surface``; costs a pass over the stored points)."""
        return self._objects_and_structure(surfaces)[0]

    def _objects_and_structure(self, surfaces: bool) -> tuple[list[SceneObject], np.ndarray | None]:
        """:meth:`objects`, and with ``surfaces`` the observed points no object claims (None
        without surfaces)."""
        out = [self.published(t) for t in sorted(self.tracks, key=lambda t: t.id) if self.shown(t)]
        seen = self.surface_points() if surfaces else None
        if seen is None:
            return out, None
        per_object, rest = split_points(seen, out, self.config.surface_pad)
        for o, pts in zip(out, per_object):
            o.surface = pts
        return out, rest

    def surface_points(self) -> np.ndarray | None:
        """(M,3) the observed surface points (voxel means seen ``surface_min_count`` times, world
        frame), not yet split among the objects (that takes :meth:`objects` with ``surfaces``);
        None when the map keeps none (``surface_voxel`` 0)."""
        return None if self.surface is None else self.surface.points(self.config.surface_min_count)

    def observed_surfaces(self) -> tuple[np.ndarray, float] | None:
        """(:meth:`surface_points`, the pad by which an object's box claims them): what
        ``ArScene.observed`` takes; None when the map keeps none."""
        pts = self.surface_points()
        return None if pts is None else (pts, float(self.config.surface_pad))

    def grid(self, inflate: bool = False) -> NavGrid:
        """The navigation grid (a copy; inflated by ``config.inflation_radius`` when ``inflate``)."""
        if self._grid is None:
            parts = []
            for t in self.tracks:
                if not self.shown(t):
                    continue
                prims = t.primitives()
                parts += [(p.center, p.size, p.rotation) for p in prims] or [(t.center, t.size, t.rotation)]
            c = self.config
            self._grid = build_grid(self.floor, parts, self.floor_z, c.agent_height, c.min_obstacle_height)
        g = self._grid
        return g.inflated(self.config.inflation_radius) if inflate else NavGrid(g.resolution, g.origin.copy(),
                                                                               g.data.copy(), g.floor_z)

    @property
    def floor_z(self) -> float:
        """World z of the floor (given, or from the per-frame estimates,
        :func:`~.grid.floor_from_estimates`; 0 before any)."""
        if self.config.floor_z is not None:
            return float(self.config.floor_z)
        if self._floor_cache is None:  # reset when the estimates change
            z = floor_from_estimates(self._floor_estimates)
            self._floor_cache = 0.0 if z is None else z
        return self._floor_cache

    def to_json(self) -> dict[str, Any]:
        """The map as a JSON-ready dict (schema in :mod:`.json_io`)."""
        objects, structure = self._objects_and_structure(True)
        return scene_to_dict(self.frame_id, self.stamp_ns, objects, self.grid(), structure)

    def save_json(self, path: str | Path) -> None:
        """Write :meth:`to_json` to ``path`` (atomically: readers never see half a file)."""
        write_json(path, self.to_json())

    @classmethod
    def from_json(cls, path_or_dict: str | Path | dict[str, Any], config: SceneConfig | None = None) -> SceneMap:
        """A map holding the objects (as confirmed tracks) and the free floor of a saved one;
        :meth:`update` keeps working on it."""
        d = load_dict(path_or_dict)
        from dataclasses import replace

        m = cls(replace(config or SceneConfig(), world_frame=str(d["frame_id"])))
        m.stamp_ns = int(d.get("stamp_ns", 0))
        for i, o in enumerate(d["objects"]):
            try:
                obj = SceneObject.from_dict(o)
            except (KeyError, TypeError, ValueError, AttributeError) as e:
                raise ValueError(f"scene JSON object {i} lacks or mistypes a field: {e!r}") from None
            m.tracks.append(_track_from_object(obj, m.config.max_weight))
            if obj.surface is not None and m.surface is not None:  # saved points passed the count test
                m.surface.add(obj.surface, weight=max(1, m.config.surface_min_count))
        structure = structure_from_dict(d)
        if len(structure) and m.surface is not None:
            m.surface.add(structure, weight=max(1, m.config.surface_min_count))
        m._next_id = max([t.id for t in m.tracks], default=0) + 1
        if "grid" in d:
            g = grid_from_dict(d["grid"])
            m.floor = FloorMemory(g.resolution)
            rows, cols = np.nonzero(g.data == 0)
            m.floor.add(g.origin + (np.stack([cols, rows], axis=1) + 0.5) * g.resolution)
            m._floor_estimates, m._floor_cache = [g.floor_z], None
        return m

    # -- steps ---------------------------------------------------------------------
    def _pose(self, T: np.ndarray | None, up_camera: np.ndarray | None) -> np.ndarray:
        if T is not None:
            T = np.asarray(T, dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f"T_world_camera must be a finite 4x4 matrix, got shape {T.shape}")
            return T
        if not self._static_warned:
            self._static_warned = True
            msg = ("scene map: no camera pose; assuming a static camera (world = camera frame turned so "
                   "that z is up, origin at the camera)")
            log.warning(msg)
            warnings.warn(msg, stacklevel=3)
        out = np.eye(4)
        out[:3, :3] = level_rotation(up_camera)
        return out

    def _observations(self, objects: Sequence[Object3D], T: np.ndarray, depth: np.ndarray | None,
                      K: np.ndarray | None) -> list[Observation]:
        size = None if depth is None else tuple(np.shape(depth))
        out = []
        for o in objects:
            if o.class_name not in CLASSES or not (o.score >= self.config.min_score):
                continue
            ob = to_observation(o, T, self.stamp_ns, K, size, depth=depth)
            if ob is None:
                log.debug("scene map: skipped a malformed detection")
                continue
            out.append(ob)
        return out

    def _assign(self, obs: list[Observation]) -> set[int]:
        """Match, fuse, start tracks; returns the ids of the tracks detected this frame."""
        c = self.config
        pairs, _, new = associate(cost_matrix(self.tracks, obs, c.class_weight), c.gate)
        matched: set[int] = set()
        for ti, di in pairs:
            self.tracks[ti].fuse(obs[di], 1.0, c.max_weight)
            matched.add(self.tracks[ti].id)
        for di in sorted(new, key=lambda j: -obs[j].weight):
            probe = Track.start(0, obs[di], 0.0)
            best, best_ov = None, 0.0
            reach = 0.5 * np.linalg.norm(probe.size)
            for t in self.tracks:
                if np.linalg.norm(t.center - probe.center) > reach + 0.5 * np.linalg.norm(t.size):
                    continue  # too far apart to overlap
                iou, ios = overlap(t, probe)
                # one object: boxes overlapping a lot, or mostly nested with agreeing classes
                # (a chair pushed under a table is nested in it but keeps its own track)
                ov = max(iou / c.merge_iou, ios / c.merge_ios if class_similarity(t, probe) >= 0.2 else 0.0)
                if ov > best_ov:
                    best, best_ov = t, ov
            if best is not None and best_ov >= 1.0:
                if best.id not in matched:  # a late match: the cost was high but the boxes overlap
                    best.fuse(obs[di], 1.0, c.max_weight)
                    matched.add(best.id)
                continue  # a second box on an object already detected this frame
            t = Track.start(self._next_id, obs[di], 0.0)
            self._next_id += 1
            self.tracks.append(t)
            matched.add(t.id)
        for t in self.tracks:
            if t.observations >= c.confirm_observations and t.weight_sum >= c.confirm_weight:
                t.confirmed = True
        return matched

    def _negative_evidence(self, matched: set[int], T: np.ndarray, depth: np.ndarray, K: np.ndarray) -> None:
        missed = [t for t in self.tracks if t.id not in matched]
        parts = [[(q.center, q.size, q.rotation) for q in t.primitives()] or [(t.center, t.size, t.rotation)]
                 for t in missed]
        gone = set()
        for t, empty in zip(missed, seen_empty_many(parts, T, depth, K, self._empty)):
            if empty is True:
                t.empty_streak += 1
            elif empty is False:
                t.empty_streak = 0
            if t.empty_streak >= self.config.delete_misses:
                log.debug("scene map: track %d seen empty, removed", t.id)
                gone.add(t.id)
        self.tracks = [t for t in self.tracks if t.id not in gone]

    def _age(self, matched: set[int]) -> None:
        for t in self.tracks:
            if t.id not in matched:
                t.frames_since_seen += 1
        self.tracks = [t for t in self.tracks
                       if t.confirmed or t.frames_since_seen <= self.config.tentative_max_age]

    def _merge(self) -> None:
        c = self.config
        while True:
            pairs, displaced = duplicates(self.tracks, c.merge_iou, c.merge_ios,
                                          displaced_iou=c.displaced_iou, displaced_share=c.displaced_share)
            if not pairs:
                break
            i, j = pairs[0]
            a, b = self.tracks[i], self.tracks[j]
            keep, gone = (a, b) if (a.confirmed, -a.id) >= (b.confirmed, -b.id) else (b, a)
            keep.absorb(gone)
            self.tracks.remove(gone)
        if displaced:
            gone_ids = {self.tracks[k].id for k in displaced}
            log.debug("scene map: displaced duplicate tracks %s dropped", sorted(gone_ids))
            self.tracks = [t for t in self.tracks if t.id not in gone_ids]

    def integrate_floor(self, T: np.ndarray, depth: np.ndarray, K: np.ndarray) -> None:
        """Add the floor seen in ``depth`` (metres; ``K`` its intrinsics) from pose ``T`` to the
        grid, and the depth points above it to the observed surfaces."""
        c = self.config
        pts = depth_points_world(depth, K, T, c.depth_stride, c.max_range)
        if c.floor_z is None:
            fz = estimate_floor_z(pts[:, 2])
            if fz is not None:
                self._floor_estimates.append(fz)
                self._floor_estimates = self._floor_estimates[-200:]
                self._floor_cache = None
        # np.compress: a boolean row selection costs several times more here
        near = np.compress(np.abs(pts[:, 2] - self.floor_z) <= c.floor_band, pts[:, :2], axis=0)
        cells = floor_cells_seen(depth, K, T, self.floor_z, c.grid_resolution, near, c.floor_band, known=self.floor)
        self.floor.add(np.concatenate([near, cells]))
        if self.surface is not None:
            self.surface.add(np.compress(pts[:, 2] > self.floor_z + c.floor_band, pts, axis=0))

    def shown(self, t: Track) -> bool:
        """Whether track ``t`` is published (:func:`published_rule`)."""
        return bool(published_rule(t.confirmed, t.restored, t.score, self.config.publish_score))

    @staticmethod
    def published(t: Track) -> SceneObject:
        """Track ``t`` as a published object: class, score and class probabilities as the track
        classifier decided them (:meth:`_decide`), else from its own class evidence and score."""
        R = t.rotation
        prims = [ScenePrimitive(p.center, p.size, p.rotation) for p in t.primitives()]
        if t.decision is not None:
            k, score, probs = t.decision
            name = CLASSES[k]
        else:
            name, score, probs = t.class_name, t.score, t.class_probs
        return SceneObject(id=t.id, class_name=name, score=float(score), center=t.center.copy(),
                           size=t.size.copy(), rotation=R, yaw=t.yaw, observations=t.observations,
                           first_seen_ns=t.first_seen_ns, last_seen_ns=t.last_seen_ns, primitives=prims,
                           face_sd=t.face_sd,
                           class_probs={c: float(p) for c, p in zip(CLASSES, probs) if p >= 0.05},
                           track_score=t.score)

    def _decide(self) -> None:
        """The track classifier's class and score for every published track (restored ones keep
        what was saved until they are observed again)."""
        for t in self.tracks:
            if not t.as_saved:
                t.decision = None
        if self.classifier is None or not self.tracks:
            return
        probs, scores = tracks_state(self.tracks)  # at once: each Track.score call costs ~15 us
        idx = np.flatnonzero(published_rule(np.array([t.confirmed for t in self.tracks]),
                                            np.array([t.restored for t in self.tracks]), scores,
                                            self.config.publish_score))
        if not len(idx):
            return
        shown = [self.tracks[i] for i in idx]
        x = tracks_features(shown, self.floor_z, (probs[idx], scores[idx]))
        for t, k, s, p in zip(shown, *self.classifier.decide(x)):
            if not t.as_saved:
                t.decision = (int(k), float(s), p)


def published_rule(confirmed: Any, restored: Any, score: Any, publish_score: float) -> Any:
    """Whether tracks are published (scalars or arrays alike): confirmed, and their own score
    (not the track classifier's) at least ``publish_score``, or restored from a saved map."""
    return confirmed & (restored | (score >= publish_score))


def disc_points(center_xy: np.ndarray, radius: float, step: float) -> np.ndarray:
    """(N, 2) points on a square lattice of spacing ``step`` inside the disc of ``radius`` about
    ``center_xy`` (world x, y, metres)."""
    r = np.arange(-radius, radius + 1e-9, step)
    xx, yy = np.meshgrid(r, r)
    inside = xx * xx + yy * yy <= radius * radius
    return np.stack([xx[inside], yy[inside]], axis=1) + np.asarray(center_xy, np.float64)[:2]


def _depth_metres(depth: np.ndarray | None, K: np.ndarray | None) -> np.ndarray | None:
    """float32 metres (NaN invalid) from metres or uint16 millimetres; None (logged) when it
    cannot be used: not 2D, or without a 3x3 K."""
    if depth is None:
        return None
    d = np.asarray(depth)
    if d.ndim != 2 or K is None or np.shape(K) != (3, 3):
        log.warning("scene map: depth must be (H, W) with a 3x3 K; depth not used this frame")
        return None
    if d.dtype == np.uint16:
        out = d.astype(np.float32) / 1000.0
        out[d == 0] = np.nan
        return out
    return d.astype(np.float32, copy=False)


def _track_from_object(o: SceneObject, max_weight: float) -> Track:
    """A confirmed track standing for a published object: its class evidence from
    ``class_probs`` (the classes left out share the rest evenly), else one-hot; its score as saved."""
    ev = np.array([max(float(o.class_probs.get(c, 0.0)), 0.0) for c in CLASSES])
    if not (np.all(np.isfinite(ev)) and 0.0 < ev.sum() <= 1.0 + 1e-3 and CLASSES[int(np.argmax(ev))] == o.class_name):
        ev = np.zeros(N_CLASSES)
        ev[CLASSES.index(o.class_name) if o.class_name in CLASSES else 0] = 1.0
    missing = ev == 0.0
    if missing.any():
        ev[missing] = max(1.0 - ev.sum(), 0.0) / missing.sum()
    ev = ev / ev.sum()
    n = max(int(o.observations), 1)
    w = min(float(n), max_weight)
    t = Track(id=int(o.id), center=np.asarray(o.center, float), size=np.asarray(o.size, float), yaw=float(o.yaw),
              class_evidence=ev * w, weight_sum=w, existence=0.0, observations=n,
              first_seen_ns=int(o.first_seen_ns), last_seen_ns=int(o.last_seen_ns),
              score_sum=o.own_score * n / float(track_score(n, n, ev.max())), confirmed=True)  # Track.score = own_score
    R = t.rotation
    t.prims_local = [((R.T @ (p.center - t.center)) / np.maximum(t.size, 1e-6),
                      (np.abs(R.T @ p.rotation) @ p.size) / np.maximum(t.size, 1e-6)) for p in o.primitives]
    t.prims_weight = w
    t.face_ss, t.face_ss_weight = w * np.asarray(o.face_sd, float).reshape(4) ** 2, w
    t.restored = t.as_saved = True
    t.decision = (int(np.argmax(ev)), float(o.score), ev)  # published as saved
    return t
