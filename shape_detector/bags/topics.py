"""Choosing a bag's input topics: colour image, depth image, camera_info (+ IMU, 2D detections).

Explicit choices are checked against the bag; missing ones are found by type, by the first
message's encoding (16UC1/32FC1 = depth) and by name (``color``/``rgb`` vs ``depth``;
``aligned_depth_to_color`` and ``registered`` preferred; camera_info next to the colour topic).
"""

from __future__ import annotations

from dataclasses import dataclass

from .source import CAMERA_INFO_T, DET2D_T, IMAGE_T, IMU_T, AnyReaderSource, BagReadError, BagSource

DEPTH_ENCODINGS = ("16UC1", "32FC1", "mono16", "64FC1")
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "rgb16", "bgr16", "rgba16", "bgra16", "8UC3")


@dataclass
class TopicSelection:
    """The input topics of a frame stream (None = not used)."""

    image: str
    depth: str
    camera_info: str | None
    imu: str | None = None
    detections2d: str | None = None

    def roles(self) -> dict[str, str]:
        """topic -> role for every selected topic."""
        out = {}
        for role in ("image", "depth", "camera_info", "imu", "detections2d"):
            topic = getattr(self, role)
            if topic:
                out[topic] = role
        return out


def _peek_encodings(source: BagSource, topics: list[str], limit: int = 400) -> dict[str, str]:
    """Encoding of the first message of each Image topic in ``topics``."""
    found: dict[str, str] = {}
    if not topics:
        return found
    if isinstance(source, AnyReaderSource):
        for t in topics:
            conns = [c for c in source.connections if c.topic == t]
            try:
                for _conn, _ts, raw in source.reader.messages(connections=conns):
                    found[t] = str(source.reader.deserialize(raw, IMAGE_T).encoding)
                    break
            except Exception:  # noqa: BLE001 - peeking is best effort
                pass
        return found
    try:
        for k, m in enumerate(source.messages(topics)):
            if m.topic not in found:
                found[m.topic] = str(source.deserialize(m.raw, IMAGE_T).encoding)
            if len(found) == len(topics) or k > limit:
                break
    except (BagReadError, AttributeError):
        pass
    finally:
        source.messages_read, source.last_time_ns = 0, None
    return found


def select_topics(
    source: BagSource,
    image: str | None = None,
    depth: str | None = None,
    camera_info: str | None = None,
    imu: str | None = None,
    detections2d: str | None = None,
) -> TopicSelection:
    """Choose the colour, depth and camera_info topics of a bag (explicit ones are checked).

    Image topics are told apart by their first message's encoding (16UC1/32FC1 = depth)
    and by name (``color``/``rgb`` vs ``depth``; ``aligned_depth_to_color`` and
    ``registered`` preferred); camera_info is the one next to the colour topic. Raises
    ValueError listing the candidates when the choice is impossible.
    """
    topics = source.topics
    listing = ", ".join(f"{t} [{ty}]" for t, ty in sorted(topics.items())) or "(none)"

    def check(t: str | None, want: str, flag: str) -> None:
        if t is None:
            return
        if t not in topics:
            raise ValueError(f"{flag} {t!r}: no such topic in the bag; topics: {listing}")
        if topics[t] != want:
            raise ValueError(f"{flag} {t!r} has type {topics[t]}, expected {want}")

    check(image, IMAGE_T, "--image")
    check(depth, IMAGE_T, "--depth")
    check(camera_info, CAMERA_INFO_T, "--camera-info")
    check(imu, IMU_T, "--imu")
    check(detections2d, DET2D_T, "--detections2d")

    if image is None or depth is None:
        image, depth = _choose_images(source, image, depth, listing)
    if camera_info is None:
        camera_info = _choose_camera_info(topics, image, listing)
    return TopicSelection(image, depth, camera_info, imu, detections2d)


def _choose_images(source: BagSource, image: str | None, depth: str | None, listing: str) -> tuple[str, str]:
    """The colour and depth topics (given ones kept) by first encoding and by name."""
    topics = source.topics
    image_topics = [t for t, ty in topics.items() if ty == IMAGE_T]
    enc = _peek_encodings(source, [t for t in image_topics if t not in (image, depth)])

    def is_depth(t: str) -> bool:
        e = enc.get(t)
        if e in ("16UC1", "32FC1", "64FC1"):
            return True
        return "depth" in t.lower() and e in (None, "mono16")

    def is_colour(t: str) -> bool:
        e = enc.get(t)
        low = t.lower()
        if "depth" in low:
            return False
        return e in COLOR_ENCODINGS or (e in (None, "mono8") and any(k in low for k in ("color", "colour", "rgb")))

    if image is None:
        cands = [t for t in image_topics if t != depth and is_colour(t)]
        if not cands:
            found = ", ".join(f"{t} [encoding {enc.get(t, 'unknown')!r}]" for t in image_topics) or "none"
            raise ValueError(
                f"no colour image topic with a supported encoding (image topics: {found}; supported colour "
                f"encodings: {', '.join(COLOR_ENCODINGS)}); topics: {listing}"
            )

        def cscore(t: str) -> tuple:
            low = t.lower()
            return (
                -(("color" in low or "colour" in low or "rgb" in low) * 2),
                -("image_raw" in low or "image_rect_color" in low),
                ("compressed" in low) + ("infra" in low) + ("ir" in low.split("/")),
                t,
            )

        image = sorted(cands, key=cscore)[0]
    if depth is None:
        cands = [t for t in image_topics if t != image and is_depth(t)]
        if not cands:
            raise ValueError(f"no depth image topic found (pass --depth); topics: {listing}")

        def dscore(t: str) -> tuple:
            low = t.lower()
            return (
                -(("aligned_depth_to_color" in low or "registered" in low) * 2),
                -("depth" in low),
                -("image_raw" in low or "image_rect" in low),
                t,
            )

        depth = sorted(cands, key=dscore)[0]
    assert image is not None and depth is not None
    return image, depth


def _choose_camera_info(topics: dict[str, str], image: str, listing: str) -> str:
    """The camera_info topic next to the colour topic (or the only one, or a colour one)."""
    infos = [t for t, ty in topics.items() if ty == CAMERA_INFO_T]
    parent = image.rsplit("/", 1)[0] if "/" in image.strip("/") else ""
    next_to = [t for t in infos if parent and t.rsplit("/", 1)[0] == parent]
    coloured = [t for t in infos if any(k in t.lower() for k in ("color", "colour", "rgb"))]
    if next_to:
        return sorted(next_to)[0]
    if len(infos) == 1:
        return infos[0]
    if coloured:
        return sorted(coloured)[0]
    if infos:
        raise ValueError(f"several camera_info topics ({', '.join(sorted(infos))}); pass --camera-info")
    raise ValueError(f"no sensor_msgs/msg/CameraInfo topic in the bag (pass --camera-info); topics: {listing}")
