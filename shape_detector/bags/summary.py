"""What a replay did (:class:`ReplaySummary`: counts, timings, damage, scene) and its progress bar."""

from __future__ import annotations

import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .topics import TopicSelection


@dataclass
class ReplaySummary:
    """What a replay did. ``frames_in``: colour images read; ``synced``: synchronised
    sets; ``frames_out``: marker messages written (one per synchronised set, empty for
    sets that could not be used - see ``skipped``); ``error``: the bag damage message when
    the input was cut short (everything before it was processed and written)."""

    in_path: str
    out_path: str
    topics: TopicSelection | None = None
    messages_in: int = 0
    frames_in: int = 0
    depth_in: int = 0
    synced: int = 0
    frames_out: int = 0
    objects: int = 0
    objects_per_class: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    detect_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    copied: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)
    notes: Counter = field(default_factory=Counter)
    recovered: bool = False
    error: str | None = None
    interrupted: str | None = None
    damage: list[str] = field(default_factory=list)
    detected: int = 0
    #: scene recording (``--scene-out`` / ``--world-frame``): None when off, else a
    #: :class:`~shape_detector.bags.scene_record.SceneStats`
    scene: Any = None

    @property
    def ok(self) -> bool:
        """No damage and no read error."""
        return self.error is None and not self.damage

    @property
    def all_skipped(self) -> bool:
        """Frames were read, but not one reached the detector."""
        return self.detected == 0 and (self.frames_in > 0 or sum(self.skipped.values()) > 0)

    @property
    def ms_per_frame(self) -> float:
        """Mean detector time per detected frame, ms."""
        return float(np.mean(self.detect_ms)) if self.detect_ms else 0.0

    def as_dict(self) -> dict[str, Any]:
        """The summary as plain JSON-able values."""
        return {
            "in": self.in_path,
            "out": self.out_path,
            "topics": None if self.topics is None else vars(self.topics),
            "messages_in": self.messages_in,
            "frames_in": self.frames_in,
            "synced": self.synced,
            "frames_out": self.frames_out,
            "objects": self.objects,
            "objects_per_class": dict(self.objects_per_class),
            "skipped": dict(self.skipped),
            "ms_per_frame": round(self.ms_per_frame, 2),
            "wall_s": round(self.wall_s, 3),
            "detected": self.detected,
            "error": self.error,
            "damage": list(self.damage),
            "interrupted": self.interrupted,
            "scene": None if self.scene is None else self.scene.as_dict(),
        }

    def format(self) -> str:
        """The summary as the lines the CLI prints."""
        t = self.topics
        lines = [f"replay {self.in_path} -> {self.out_path}"]
        if t is not None:
            lines.append(f"  topics: image {t.image}, depth {t.depth}, camera_info {t.camera_info}"
                         + (f", imu {t.imu}" if t.imu else "") + (f", detections2d {t.detections2d}" if t.detections2d else ""))
        lines.append(
            f"  frames: {self.frames_in} in / {self.synced} synchronised / {self.frames_out} out"
            f"   ({self.messages_in} messages read{', recovered sequentially' if self.recovered else ''})"
        )
        if self.skipped:
            reasons = ", ".join(f"{k}: {v}" for k, v in self.skipped.most_common())
            lines.append(f"  skipped: {sum(self.skipped.values())} ({reasons})")
        per = ", ".join(f"{k} {v}" for k, v in self.objects_per_class.most_common()) or "none"
        lines.append(f"  objects: {self.objects} ({per})")
        if self.detect_ms:
            lines.append(
                f"  detector: {self.ms_per_frame:.1f} ms/frame (p95 {np.percentile(self.detect_ms, 95):.1f} ms); "
                f"wall {self.wall_s:.2f} s"
            )
        if self.scene is not None:
            lines.append(f"  scene: {self.scene.format()}")
        for note, n in self.notes.most_common(5):
            lines.append(f"  note ({n}x): {note}")
        for topic, why in self.skipped_topics.items():
            lines.append(f"  not copied: {topic}: {why}")
        for d in self.damage:
            lines.append(f"  DAMAGED (skipped): {d}")
        if self.error:
            lines.append(f"  ERROR: {self.error}")
            lines.append(f"  the {self.frames_out} frame(s) before the damage were written to {self.out_path}")
        if self.interrupted:
            lines.append(f"  interrupted by {self.interrupted}: {self.frames_out} frame(s) written to {self.out_path}")
        return "\n".join(lines)


class Progress:
    """A one-line progress bar on stderr (redrawn at most 10x a second)."""

    def __init__(self, total: int | None, enabled: bool, stream: Any = None) -> None:
        self.total = total
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = 0.0
        self._last_pct = -1
        self.n = 0
        self.frames = 0

    def update(self, n: int, frames: int, force: bool = False) -> None:
        """``n`` messages read, ``frames`` written; redrawn when due (or ``force``)."""
        self.n, self.frames = n, frames
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        if self.total:
            frac = min(1.0, n / self.total)
            if not self.tty:  # log every 10 %
                pct = int(frac * 10)
                if pct == self._last_pct and not force:
                    return
                self._last_pct = pct
                self.stream.write(f"replay: {100 * frac:3.0f}%  {n}/{self.total} messages, {frames} frames\n")
                self.stream.flush()
                return
            width = 30
            bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
            self.stream.write(f"\r[{bar}] {100 * frac:3.0f}%  {n}/{self.total} msgs  {frames} frames")
        else:
            if not self.tty and not force:
                return
            self.stream.write(f"\r{n} msgs  {frames} frames" if self.tty else f"replay: {n} messages, {frames} frames\n")
        self.stream.flush()

    def done(self) -> None:
        """Draw the final state and end the line."""
        if self.enabled:
            self.update(self.n, self.frames, force=True)
            if self.tty:
                self.stream.write("\n")
                self.stream.flush()
