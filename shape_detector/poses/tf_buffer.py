"""A small TF buffer: a tree of frames with stamped (or static) parent -> child transforms.

Pure numpy, no rclpy. ``lookup(target, source, stamp)`` returns ``T_target_source`` (4x4: a point
in ``source`` coordinates mapped into ``target``) through chains of transforms such as
``odom -> base_link -> camera_link -> camera_color_optical_frame``. Dynamic transforms are
interpolated between the two stored stamps around the request (linear translation, slerp
rotation); a stamp outside a link's stored range is an error, never an extrapolation.
Stamps are int nanoseconds.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .quaternion import invert_transform, make_transform, normalize_quaternion, slerp


class TransformLookupError(LookupError):
    """A transform could not be looked up; the message names the missing link or stamp."""


class FrameNotFoundError(TransformLookupError):
    """A frame is unknown to the buffer, or the two frames are not connected."""


class ExtrapolationError(TransformLookupError):
    """The requested stamp is outside the stored history of one link of the chain."""


@dataclass
class _Link:
    """The transform ``parent -> child``: one static value or a stamp-sorted history."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)
    quaternions: list[np.ndarray] = field(default_factory=list)

    def insert(self, stamp_ns: int, t: np.ndarray, q: np.ndarray) -> None:
        if self.static:
            self.stamps, self.translations, self.quaternions = [stamp_ns], [t], [q]
            return
        i = bisect.bisect_left(self.stamps, stamp_ns)
        if i < len(self.stamps) and self.stamps[i] == stamp_ns:  # same stamp again: newest wins
            self.translations[i], self.quaternions[i] = t, q
            return
        self.stamps.insert(i, stamp_ns)
        self.translations.insert(i, t)
        self.quaternions.insert(i, q)

    def prune(self, oldest_ns: int) -> None:
        """Drop dynamic entries older than ``oldest_ns`` (keeps at least one)."""
        if self.static:
            return
        k = min(bisect.bisect_left(self.stamps, oldest_ns), len(self.stamps) - 1)
        if k > 0:
            del self.stamps[:k], self.translations[:k], self.quaternions[:k]

    def at(self, child: str, stamp_ns: int | None) -> np.ndarray:
        """``T_parent_child`` at ``stamp_ns`` (None: the newest)."""
        if self.static or stamp_ns is None:
            return make_transform(self.translations[-1], self.quaternions[-1])
        s = self.stamps
        if stamp_ns < s[0] or stamp_ns > s[-1]:
            raise ExtrapolationError(
                f"transform {self.parent} -> {child} at {stamp_ns} ns is outside its stored range "
                f"[{s[0]}, {s[-1]}] ns"
            )
        i = bisect.bisect_left(s, stamp_ns)
        if s[i] == stamp_ns:
            return make_transform(self.translations[i], self.quaternions[i])
        t0, t1 = s[i - 1], s[i]
        a = (stamp_ns - t0) / float(t1 - t0)
        trans = (1.0 - a) * self.translations[i - 1] + a * self.translations[i]
        return make_transform(trans, slerp(self.quaternions[i - 1], self.quaternions[i], a))


class TransformBuffer:
    """Stamped transforms between named frames, looked up through chains.

    ``max_history_ns`` bounds how far back dynamic transforms are kept, relative to the newest
    stamp of the same link (None: keep everything, as offline replay does).
    """

    def __init__(self, max_history_ns: int | None = 10_000_000_000) -> None:
        if max_history_ns is not None and max_history_ns <= 0:
            raise ValueError(f"max_history_ns={max_history_ns} must be positive or None")
        self.max_history_ns = max_history_ns
        self._links: dict[str, _Link] = {}  # child frame -> link to its parent

    def add(
        self,
        parent: str,
        child: str,
        stamp_ns: int,
        translation: Any,
        quaternion: Any,
        static: bool = False,
    ) -> None:
        """Store ``T_parent_child`` at ``stamp_ns``: translation (3,) m, quaternion ``(x, y, z, w)``.

        A frame has one parent: a new parent for a known child replaces the old link.
        ``ValueError`` for empty or equal frame names and non-finite values.
        """
        parent, child = str(parent).lstrip("/"), str(child).lstrip("/")
        if not parent or not child:
            raise ValueError(f"empty frame name in transform {parent!r} -> {child!r}")
        if parent == child:
            raise ValueError(f"transform from frame {parent!r} to itself")
        t = np.asarray(translation, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(t)):
            raise ValueError(f"non-finite translation in transform {parent} -> {child}")
        q = normalize_quaternion(quaternion)
        link = self._links.get(child)
        if link is None or link.parent != parent or link.static != bool(static):
            link = _Link(parent=parent, static=bool(static))
            self._links[child] = link
        link.insert(int(stamp_ns), t, q)
        if self.max_history_ns is not None and not link.static:
            link.prune(link.stamps[-1] - self.max_history_ns)

    def add_tf_message(self, msg: Any, static: bool = False) -> int:
        """Store every transform of a ``tf2_msgs/TFMessage`` (rclpy or rosbags); returns how many.

        Malformed entries (empty frames, zero quaternions) are skipped, not raised.
        """
        from .sources import transform_stamped_fields

        n = 0
        for ts in getattr(msg, "transforms", ()):
            try:
                parent, child, stamp_ns, t, q = transform_stamped_fields(ts)
                self.add(parent, child, stamp_ns, t, q, static=static)
            except (ValueError, TypeError, AttributeError):
                continue
            n += 1
        return n

    def frames(self) -> set[str]:
        """Every frame named by a stored transform."""
        return set(self._links) | {link.parent for link in self._links.values()}

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        while path[-1] in self._links:
            path.append(self._links[path[-1]].parent)
            if len(path) > len(self._links) + 1:  # a cycle can only come from inconsistent input
                raise FrameNotFoundError(f"transform tree has a cycle through frame {frame!r}")
        return path

    def _chain(self, path: list[str], stop: str, stamp_ns: int | None) -> np.ndarray:
        """``T_stop_path[0]``: the product of links from ``path[0]`` up to ``stop``."""
        T = np.eye(4)
        for child in path:
            if child == stop:
                break
            T = self._links[child].at(child, stamp_ns) @ T
        return T

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int | None) -> np.ndarray:
        """(4,4) ``T_target_source`` at ``stamp_ns`` (None: the newest of every link).

        Raises :class:`FrameNotFoundError` when a frame is unknown or the frames are in
        different trees (the message names each side's root), :class:`ExtrapolationError`
        when ``stamp_ns`` is outside a link's stored history.
        """
        target, source = str(target_frame).lstrip("/"), str(source_frame).lstrip("/")
        if target == source:
            return np.eye(4)
        known = self.frames()
        for name in (target, source):
            if name not in known:
                raise FrameNotFoundError(f"frame {name!r} is not in the transform buffer (known: {sorted(known)})")
        up_source = self._path_to_root(source)
        up_target = self._path_to_root(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            raise FrameNotFoundError(
                f"no transform chain between {target!r} and {source!r}: {source!r} has root "
                f"{up_source[-1]!r}, {target!r} has root {up_target[-1]!r} (missing link: no "
                f"transform connects {up_source[-1]!r} and {up_target[-1]!r})"
            )
        T_common_source = self._chain(up_source, common, stamp_ns)
        T_common_target = self._chain(up_target, common, stamp_ns)
        return invert_transform(T_common_target) @ T_common_source

    def can_transform(self, target_frame: str, source_frame: str, stamp_ns: int | None) -> bool:
        """True when :meth:`lookup` would succeed."""
        try:
            self.lookup(target_frame, source_frame, stamp_ns)
        except TransformLookupError:
            return False
        return True
