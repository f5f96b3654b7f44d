"""Scene tracks: one piece of furniture in the world frame, fused over observations.

World frame: z up, metres. A box is ``center`` (3,), ``size`` (l, w, h) with h along up,
and ``yaw`` (radians) of its x axis about up. Primitives are stored in the box's own
unit frame (centre and size divided by the box size, rotation relative to the box) so
they follow the fused box.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..classes import CLASSES
from ..types import Cuboid

N_CLASSES = len(CLASSES)
#: metres: an observation this far from an established track's centre moves its box half as much
OUTLIER_SCALE = 0.2
#: fusion weight after which a track's box is established
OUTLIER_AFTER = 0.3
_CLASS_INDEX = {c: i for i, c in enumerate(CLASSES)}
#: horizontal face order (-x, +x, -y, +y) of a box after k quarter turns (:func:`align_yaw`):
#: row k lists, for each face of the turned box, the face of the original it is
_FACE_TURNS = np.array([[0, 1, 2, 3], [2, 3, 1, 0], [1, 0, 3, 2], [3, 2, 0, 1]])


def rotz(yaw: float) -> np.ndarray:
    """3x3 rotation about z by ``yaw`` (radians)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wrap(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return float((a + np.pi) % (2.0 * np.pi) - np.pi)


@dataclass
class Observation:
    """One detection in the world frame, ready to fuse.

    ``weight``: detector confidence times visible share (0..1]; ``class_probs`` (N_CLASSES,)
    sums to 1; ``prims_local``: list of (center (3,), size (3,)) along the box axes in box
    units (a primitive is stored as its extent along the box's axes).
    """

    class_name: str
    score: float
    center: np.ndarray
    size: np.ndarray
    yaw: float
    weight: float
    class_probs: np.ndarray
    prims_local: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    stamp_ns: int = 0


def align_yaw(yaw: float, size: np.ndarray, ref_yaw: float) -> tuple[float, np.ndarray, int]:
    """Re-express a box (yaw, size) by the quarter turn closest to ``ref_yaw``: a box is the
    same box after a 90 degree turn with its length and width swapped. Returns the new yaw,
    size and the number of quarter turns applied (0..3)."""
    k = int(np.round(wrap(ref_yaw - yaw) / (0.5 * np.pi))) % 4
    out = np.asarray(size, dtype=np.float64).copy()
    if k % 2:
        out[[0, 1]] = out[[1, 0]]
    return wrap(yaw + k * 0.5 * np.pi), out, k


def _turn_prims(prims: list, k: int) -> list:
    """Box-unit primitives re-expressed after a box turn of ``k`` quarter turns (box axes
    rotated by ``+k*90`` degrees, so local coordinates rotate by ``-k*90``)."""
    if k == 0:
        return prims
    R = np.round(rotz(-k * 0.5 * np.pi))
    out = []
    for c, s in prims:
        s2 = np.asarray(s, dtype=np.float64).copy()
        if k % 2:
            s2[[0, 1]] = s2[[1, 0]]
        out.append((R @ np.asarray(c, dtype=np.float64), s2))
    return out


@dataclass
class Track:
    """A tracked object. ``class_evidence`` (N_CLASSES,) accumulates weighted class
    probabilities; ``existence`` is a log-odds that grows with consistent observations and
    drops on negative evidence; ``confirmed`` once seen often enough."""

    id: int
    center: np.ndarray
    size: np.ndarray
    yaw: float
    class_evidence: np.ndarray
    weight_sum: float
    existence: float
    observations: int
    first_seen_ns: int
    last_seen_ns: int
    score_sum: float = 0.0
    prims_local: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    prims_weight: float = 0.0
    confirmed: bool = False
    misses_in_view: int = 0
    #: consecutive frames in which the box was in view and seen empty
    empty_streak: int = 0
    frames_since_seen: int = 0
    #: (4,) weighted sums of squared deviations of the observed -x, +x, -y, +y faces from the
    #: fused ones (m^2), and their total weight: the faces' spread, :attr:`face_sd`
    face_ss: np.ndarray = field(default_factory=lambda: np.zeros(4))
    face_ss_weight: float = 0.0
    #: the map's track classifier's (class index, score, (N_CLASSES,) class probabilities), or
    #: None: the class evidence and :attr:`score` are published
    decision: tuple[int, float, np.ndarray] | None = None
    #: restored from a saved map: published whatever its score (it was when saved)
    restored: bool = False
    #: restored and not observed since: :attr:`decision` is the saved class and score
    as_saved: bool = False

    @property
    def class_name(self) -> str:
        """The class with the most accumulated evidence."""
        return CLASSES[int(np.argmax(self.class_evidence))]

    @property
    def class_probs(self) -> np.ndarray:
        """(N_CLASSES,) the class evidence normalised to sum 1 (uniform without evidence)."""
        return evidence_probs(self.class_evidence)

    @property
    def score(self) -> float:
        """Mean detector confidence, scaled up with the number of observations and by how
        consistent the class evidence is (0..1)."""
        return float(track_score(self.score_sum, self.observations, self.class_probs.max()))

    @property
    def rotation(self) -> np.ndarray:
        """3x3 box axes in the world frame (columns)."""
        return rotz(self.yaw)

    @property
    def face_sd(self) -> np.ndarray:
        """(4,) weighted standard deviation (m) of where the observations put the box's -x, +x,
        -y, +y faces (along its axes); zeros after a single observation."""
        if self.face_ss_weight <= 0.0:
            return np.zeros(4)
        return np.sqrt(np.maximum(self.face_ss, 0.0) / self.face_ss_weight)

    def primitives(self) -> list[Cuboid]:
        """The fused primitives as world-frame cuboids."""
        R = self.rotation
        out = []
        for c, s in self.prims_local:
            out.append(Cuboid(self.center + R @ (c * self.size), s * self.size, R))
        return out

    @classmethod
    def start(cls, tid: int, ob: Observation, existence: float) -> Track:
        """A new (unconfirmed) track with id ``tid`` from its first observation."""
        return cls(id=tid, center=ob.center.copy(), size=ob.size.copy(), yaw=ob.yaw,
                   class_evidence=ob.class_probs * ob.weight, weight_sum=ob.weight, existence=existence,
                   observations=1, first_seen_ns=ob.stamp_ns, last_seen_ns=ob.stamp_ns, score_sum=ob.score,
                   prims_local=list(ob.prims_local), prims_weight=ob.weight, face_ss_weight=ob.weight)

    def fuse(self, ob: Observation, existence_gain: float, max_weight: float) -> None:
        """Fold one observation into the track: weighted running means of centre, size and
        yaw (after aligning the observation's quarter turn to the track), class evidence,
        primitives. ``max_weight`` caps the accumulated weight so the box keeps adapting."""
        yaw, size, k = align_yaw(ob.yaw, ob.size, self.yaw)
        w0, w = min(self.weight_sum, max_weight), ob.weight
        # an established box moves less for an observation far from it (robust mean)
        d = float(np.linalg.norm(ob.center - self.center))
        trust = 1.0 / (1.0 + (d / OUTLIER_SCALE) ** 2) if self.weight_sum >= OUTLIER_AFTER else 1.0
        a = w * trust / (w0 + w * trust)
        # spread of the faces (Welford's update with the fused box as the running mean)
        R = self.rotation
        seen, fused = _faces(ob.center, size, R, self.center), _faces(self.center, self.size, R, self.center)
        self.face_ss = self.face_ss + w * (1.0 - a) * (seen - fused) ** 2
        self.face_ss_weight += w
        self.center = self.center + a * (ob.center - self.center)
        self.size = self.size + a * (size - self.size)
        self.yaw = wrap(self.yaw + a * wrap(yaw - self.yaw))
        self.class_evidence = self.class_evidence + ob.class_probs * w
        self.weight_sum = w0 + w
        self.existence += existence_gain
        self.observations += 1
        self.score_sum += ob.score
        self.last_seen_ns = max(self.last_seen_ns, ob.stamp_ns)
        self.first_seen_ns = min(self.first_seen_ns, ob.stamp_ns)
        self._fuse_prims(_turn_prims(ob.prims_local, k), w)
        self.frames_since_seen = 0
        self.empty_streak = 0
        self.as_saved = False

    def _fuse_prims(self, prims: list, w: float) -> None:
        """Average primitives part by part when both sets have the same number of parts
        (paired by nearest centre); otherwise keep the set of the heavier observation."""
        if not prims:
            return
        if len(prims) != len(self.prims_local) or not self.prims_local:
            if w >= 0.8 * self.prims_weight or not self.prims_local:
                self.prims_local, self.prims_weight = list(prims), w
            return
        a = np.stack([p[0] for p in self.prims_local])
        b = np.stack([p[0] for p in prims])
        rows, cols = linear_sum_assignment(np.linalg.norm(a[:, None] - b[None], axis=2))
        f = w / (self.prims_weight + w)
        out = list(self.prims_local)
        for r, c in zip(rows, cols):
            c0, s0 = out[r]
            c1, s1 = prims[c]
            out[r] = (c0 + f * (c1 - c0), s0 + f * (s1 - s0))
        self.prims_local = out
        self.prims_weight = min(self.prims_weight + w, 50.0)

    def absorb(self, other: Track) -> None:
        """Merge a duplicate track into this one (weights add; this id is kept)."""
        yaw, size, k = align_yaw(other.yaw, other.size, self.yaw)
        w0, w1 = self.weight_sum, other.weight_sum
        a = w1 / max(w0 + w1, 1e-9)
        self._absorb_spread(other, k, size)
        self.center = self.center + a * (other.center - self.center)
        self.size = self.size + a * (size - self.size)
        self.yaw = wrap(self.yaw + a * wrap(yaw - self.yaw))
        self.class_evidence = self.class_evidence + other.class_evidence
        self.weight_sum = w0 + w1
        self.existence = max(self.existence, other.existence)
        self.restored = self.restored or other.restored
        self.as_saved = self.as_saved and other.as_saved
        self.observations += other.observations
        self.score_sum += other.score_sum
        self.first_seen_ns = min(self.first_seen_ns, other.first_seen_ns)
        self.last_seen_ns = max(self.last_seen_ns, other.last_seen_ns)
        self.confirmed = self.confirmed or other.confirmed
        if other.prims_weight > self.prims_weight:
            self.prims_local, self.prims_weight = _turn_prims(other.prims_local, k), other.prims_weight

    def _absorb_spread(self, other: Track, k: int, size: np.ndarray) -> None:
        """Pool the face spreads of a merged pair (``other`` turned by ``k`` quarter turns, its
        size then ``size``), each about its own box, plus the two boxes' disagreement; called
        before this box moves."""
        R = self.rotation
        a = _faces(self.center, self.size, R, self.center)
        b = _faces(other.center, size, R, self.center)
        wa, wb = self.face_ss_weight, other.face_ss_weight
        wa_, wb_ = max(wa, 1e-9), max(wb, 1e-9)
        self.face_ss = self.face_ss + other.face_ss[_FACE_TURNS[k % 4]] + wa_ * wb_ / (wa_ + wb_) * (a - b) ** 2
        self.face_ss_weight = wa + wb


def track_score(score_sum: Any, observations: Any, top_prob: Any) -> Any:
    """:attr:`Track.score` from its parts (scalars or arrays alike): the mean detector
    confidence times ``0.5 + 0.5 * top_prob`` (the top class's share of the evidence) times
    ``1 - exp(-observations / 3)``."""
    n = np.maximum(observations, 1)
    return score_sum / n * (0.5 + 0.5 * top_prob) * (1.0 - np.exp(-np.asarray(observations, float) / 3.0))


def evidence_probs(evidence: np.ndarray) -> np.ndarray:
    """Class evidence (..., N_CLASSES) normalised to sum 1 along its last axis (uniform where
    there is none)."""
    ev = np.asarray(evidence, float)
    tot = ev.sum(-1, keepdims=True)
    return np.where(tot > 0, ev / np.where(tot > 0, tot, 1.0), 1.0 / N_CLASSES)


def tracks_state(tracks: Sequence[Track]) -> tuple[np.ndarray, np.ndarray]:
    """(N, N_CLASSES) :attr:`Track.class_probs` and (N,) :attr:`Track.score` of ``tracks`` at once."""
    probs = evidence_probs(np.array([t.class_evidence for t in tracks], float).reshape(-1, N_CLASSES))
    obs = np.array([t.observations for t in tracks], float)
    return probs, track_score(np.array([t.score_sum for t in tracks], float), obs, probs.max(1))


def _faces(center: np.ndarray, size: np.ndarray, R: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4,) -x, +x, -y, +y faces of a box (centre, size) along the axes ``R`` from ``origin``."""
    d = R.T @ (center - origin)
    return np.array([d[0] - 0.5 * size[0], d[0] + 0.5 * size[0], d[1] - 0.5 * size[1], d[1] + 0.5 * size[1]])


def class_probs_of(class_name: str, score: float, class_scores: np.ndarray | None) -> np.ndarray:
    """Normalised class distribution of a detection: its calibrated class scores when
    available, else its label with the remaining mass spread over the others."""
    if class_scores is not None:
        p = np.clip(np.asarray(class_scores, dtype=np.float64).reshape(-1), 0.0, None)
        if p.shape[0] == N_CLASSES and p.sum() > 0:
            return p / p.sum()
    p = np.full(N_CLASSES, 0.0)
    i = _CLASS_INDEX.get(class_name)
    if i is None:
        return np.full(N_CLASSES, 1.0 / N_CLASSES)
    conf = float(np.clip(score, 0.5, 0.95))
    p[:] = (1.0 - conf) / (N_CLASSES - 1)
    p[i] = conf
    return p
