"""Bags in and out: synchronised RGB-D frames from rosbag2 / ROS 1 bags, and the output MCAP.

Reading (:func:`open_bag`, :class:`BagFrameReader`): rosbag2 directories or single files
(MCAP or sqlite3) and ROS 1 ``.bag`` files through rosbags' ``AnyReader`` (a default
typestore covers bags without embedded definitions). A truncated or unfinalised MCAP
(no summary / footer, e.g. a recorder that was killed) is read sequentially up to the
damage. Frames are paired with the same :class:`~shape_detector.sync.ApproximateTimeSynchronizer`
as the live node; each frame gets the ``camera_info`` nearest its stamp. On damage the
frame generator first yields every frame completed before it, then raises
:class:`BagReadError`.

Frame preparation (:func:`prepare_frame`, shared with the node): message triple ->
``rgb, depth (m, NaN invalid), K`` with size checks, intrinsics rescaling and a
:class:`FrameError` that says what is wrong for input that cannot be used.

Writing: :class:`~shape_detector.bags.output.OutputBag` (re-exported here), a rosbag2
MCAP with CRC-checked chunks (metadata version 8, readable by Jazzy's ``ros2 bag``,
Foxglove and RViz) holding the input topics plus ``/shape_detector/markers`` and
``/shape_detector/detections`` (vision_msgs definitions registered with rosbags).
"""

from __future__ import annotations

import mmap
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .sync import ApproximateTimeSynchronizer, header_stamp_ns

IMAGE_T = "sensor_msgs/msg/Image"
CAMERA_INFO_T = "sensor_msgs/msg/CameraInfo"
IMU_T = "sensor_msgs/msg/Imu"
DET2D_T = "vision_msgs/msg/Detection2DArray"
MARKERS_T = "visualization_msgs/msg/MarkerArray"
DET3D_T = "vision_msgs/msg/Detection3DArray"

MARKERS_TOPIC = "/shape_detector/markers"
DETECTIONS_TOPIC = "/shape_detector/detections"

DEPTH_ENCODINGS = ("16UC1", "32FC1", "mono16", "64FC1")
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "rgb16", "bgr16", "rgba16", "bgra16", "8UC3")


class BagReadError(RuntimeError):
    """A bag could not be read (completely). ``messages_read`` messages (up to log time
    ``last_time_ns``) were read before the damage."""

    def __init__(self, path: Any, reason: str, messages_read: int = 0, last_time_ns: int | None = None) -> None:
        self.path = str(path)
        self.reason = reason
        self.messages_read = messages_read
        self.last_time_ns = last_time_ns
        where = f" after {messages_read} message(s)" if messages_read else ""
        if last_time_ns is not None:
            where += f" (last good log time {last_time_ns / 1e9:.3f} s)"
        super().__init__(f"bag {self.path!r} is damaged or unreadable{where}: {reason}")


class FrameError(ValueError):
    """A synchronised message set that cannot be turned into a frame; ``kind`` is a short
    machine-readable reason (``camera_info``, ``encoding``, ``size``, ``empty``...)."""

    def __init__(self, kind: str, message: str) -> None:
        self.kind = kind
        super().__init__(message)


# =====================================================================================
# frame preparation (shared with the node)
# =====================================================================================


@dataclass
class PreparedFrame:
    """A frame ready for ``ShapeDetector.detect``: RGB ``(H, W, 3)`` uint8, depth
    ``(H, W)`` float32 metres (NaN = invalid), intrinsics ``K`` of that resolution,
    ``boxes2d`` (external proposals, scaled to that resolution) and ``notes`` about
    non-fatal fixes (rescaled intrinsics, invalid depth...)."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    stamp_ns: int
    frame_id: str
    boxes2d: list | None = None
    notes: list[str] = field(default_factory=list)
    valid_depth_fraction: float = 1.0


def _size_str(w: int, h: int) -> str:
    return f"{w}x{h}"


def _same_aspect(w1: int, h1: int, w2: int, h2: int, tol: float = 0.02) -> bool:
    return abs((w1 / h1) / (w2 / h2) - 1.0) <= tol


def prepare_frame(
    image: Any,
    depth: Any,
    camera_info: Any,
    *,
    depth_scale: float | None = None,
    size_mismatch: str = "rescale",
    detections2d: Any = None,
) -> PreparedFrame:
    """Turn an (image, depth, camera_info) message set into a :class:`PreparedFrame`.

    * ``depth_scale``: metres per raw unit for integer depth (None/0 = by encoding:
      16UC1 millimetres, 32FC1 metres); NaN / Inf / <= 0 depth becomes NaN.
    * camera_info of another resolution than the colour image (same aspect ratio):
      intrinsics rescaled. Depth of another resolution than the colour image: with
      ``size_mismatch='rescale'`` (and the same aspect ratio) the colour image is resized
      to the depth resolution and K scaled; with ``'skip'`` (or different aspect ratios)
      a :class:`FrameError` naming both sizes.
    * ``detections2d``: a vision_msgs Detection2DArray giving external 2D proposals.

    Raises :class:`FrameError` for missing camera_info, unusable encodings, all-zero /
    non-finite K, empty images and irreconcilable sizes.
    """
    import cv2

    from msg_conversion.camera_info import camera_info_size, camera_info_to_K, scale_K
    from msg_conversion.image import image_to_depth, image_to_rgb

    if size_mismatch not in ("rescale", "skip"):
        raise ValueError(f"size_mismatch must be 'rescale' or 'skip', got {size_mismatch!r}")
    if image is None or depth is None:
        raise FrameError("missing", "colour or depth image missing")
    stamp = header_stamp_ns(image)
    frame_id = str(getattr(getattr(image, "header", None), "frame_id", "") or "")
    notes: list[str] = []
    if camera_info is None:
        raise FrameError("camera_info", "no camera_info received yet: cannot interpret the images without intrinsics")
    for name, msg in (("colour", image), ("depth", depth)):
        try:
            w, h = int(msg.width), int(msg.height)
        except (AttributeError, TypeError, ValueError) as e:
            raise FrameError("malformed", f"{name} image has no valid width/height: {e}") from None
        if w <= 0 or h <= 0:
            raise FrameError("empty", f"{name} image is empty ({_size_str(w, h)})")
    try:
        rgb = image_to_rgb(image)
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("encoding", f"colour image unusable: {e}") from None
    try:
        scale = depth_scale if depth_scale else None
        dep = image_to_depth(depth, scale)
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("encoding", f"depth image unusable: {e}") from None
    try:
        K = camera_info_to_K(camera_info)
        ci_w, ci_h = camera_info_size(camera_info)
    except (ValueError, TypeError, AttributeError) as e:
        raise FrameError("camera_info", f"camera_info unusable: {e}") from None

    h, w = rgb.shape[:2]
    if ci_w > 0 and ci_h > 0 and (ci_w, ci_h) != (w, h):
        if not _same_aspect(ci_w, ci_h, w, h) or size_mismatch == "skip":
            raise FrameError(
                "size",
                f"camera_info is {_size_str(ci_w, ci_h)} but the colour image is {_size_str(w, h)} "
                + ("(different aspect ratio, cannot rescale the intrinsics)" if size_mismatch == "rescale" else "(size_mismatch=skip)"),
            )
        K = scale_K(K, w / ci_w, h / ci_h)
        notes.append(f"camera_info is {_size_str(ci_w, ci_h)}, colour image {_size_str(w, h)}: intrinsics rescaled")

    boxes2d = None
    if detections2d is not None:
        from msg_conversion.detections import detection2d_array_to_boxes

        try:
            boxes2d = list(detection2d_array_to_boxes(detections2d))
        except (ValueError, TypeError, AttributeError) as e:
            raise FrameError("detections2d", f"Detection2DArray unusable: {e}") from None

    dh, dw = dep.shape[:2]
    if (dw, dh) != (w, h):
        if size_mismatch == "skip" or not _same_aspect(dw, dh, w, h):
            why = "(size_mismatch=skip)" if size_mismatch == "skip" else "(different aspect ratio, cannot rescale)"
            raise FrameError(
                "size", f"depth image is {_size_str(dw, dh)} but the colour image is {_size_str(w, h)} {why}"
            )
        sx, sy = dw / w, dh / h
        interp = cv2.INTER_AREA if sx < 1.0 else cv2.INTER_LINEAR
        rgb = cv2.resize(rgb, (dw, dh), interpolation=interp)
        K = scale_K(K, sx, sy)
        if boxes2d is not None:
            boxes2d = [(b[0] * sx, b[1] * sy, b[2] * sx, b[3] * sy, *b[4:]) for b in boxes2d]
        notes.append(
            f"depth image is {_size_str(dw, dh)}, colour image {_size_str(w, h)}: colour resized to "
            f"{_size_str(dw, dh)} and intrinsics rescaled"
        )
    valid = np.isfinite(dep)
    frac = float(valid.mean()) if dep.size else 0.0
    if frac == 0.0:
        notes.append("depth image has no valid pixels")
    return PreparedFrame(
        rgb=np.ascontiguousarray(rgb),
        depth=dep,
        K=K,
        stamp_ns=int(stamp or 0),
        frame_id=frame_id,
        boxes2d=boxes2d,
        notes=notes,
        valid_depth_fraction=frac,
    )


# =====================================================================================
# reading
# =====================================================================================


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


@dataclass
class SyncedFrame:
    """One synchronised set read from a bag (messages deserialised, not yet decoded).

    ``index``: 0-based count of synchronised sets; ``stamp_ns``/``frame_id``: the colour
    image's header; ``log_time_ns``: bag time of the message that completed the set;
    ``up``: low-passed IMU gravity-up (camera optical frame) when an IMU topic is used.
    """

    index: int
    stamp_ns: int
    frame_id: str
    image: Any
    depth: Any
    camera_info: Any | None
    detections2d: Any | None = None
    up: np.ndarray | None = None
    log_time_ns: int = 0

    def prepare(self, depth_scale: float | None = None, size_mismatch: str = "rescale") -> PreparedFrame:
        return prepare_frame(
            self.image,
            self.depth,
            self.camera_info,
            depth_scale=depth_scale,
            size_mismatch=size_mismatch,
            detections2d=self.detections2d,
        )


@dataclass
class RawMessage:
    """One message as stored: topic, ROS 2 type name, log time, serialized bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    raw: bytes
    connection: Any = None


class BagSource:
    """Sequential access to one bag's messages (base of the two readers)."""

    path: Path
    is_ros1: bool = False
    recovered: bool = False
    topics: dict[str, str]
    message_count: int | None = None
    typestore: Any = None
    messages_read: int = 0
    last_time_ns: int | None = None
    #: damaged chunks skipped while reading (``shape_detector.bags.mcap_check.ChunkDamage``)
    damage: Sequence[Any] = ()

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        raise NotImplementedError

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> "BagSource":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class _AnyReaderSource(BagSource):
    def __init__(self, path: Path, reader: Any) -> None:
        self.path = path
        self.reader = reader
        self.is_ros1 = not reader.is2
        self.typestore = reader.typestore
        self.topics = {c.topic: c.msgtype for c in reader.connections}
        self.message_count = int(reader.message_count)
        self.connections = list(reader.connections)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        wanted = set(topics) if topics is not None else None
        conns = [c for c in self.connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        try:
            for conn, t, raw in self.reader.messages(connections=conns):
                self.messages_read += 1
                self.last_time_ns = t
                yield RawMessage(conn.topic, conn.msgtype, t, bytes(raw), conn)
        except GeneratorExit:
            raise
        except Exception as e:  # noqa: BLE001 - any reader failure is bag damage
            raise BagReadError(self.path, f"{type(e).__name__}: {e}", self.messages_read, self.last_time_ns) from e

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        try:
            return self.reader.deserialize(raw, msgtype)
        except Exception as e:  # noqa: BLE001
            raise BagReadError(
                self.path, f"cannot deserialise a {msgtype} message: {type(e).__name__}: {e}", self.messages_read, self.last_time_ns
            ) from e

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception:  # noqa: BLE001
            pass


# --- tolerant sequential MCAP reading (truncated / unfinalised files) -----------------

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_FOOTER, _OP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x02, 0x0F
_OP_MESSAGE_INDEX = 0x07


class _Truncated(Exception):
    pass


def _mcap_str(buf: bytes, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, off)
    off += 4
    if off + n > len(buf):
        raise _Truncated("string past end of record")
    return bytes(buf[off : off + n]).decode("utf-8", "replace"), off + n


def _iter_records(buf: bytes, partial_ok: bool) -> Iterator[tuple[int, bytes]]:
    """(opcode, content) of the records in ``buf``; a cut-off last record ends the
    iteration when ``partial_ok``, else raises :class:`_Truncated`."""
    off, n = 0, len(buf)
    while off < n:
        if off + 9 > n:
            if partial_ok:
                return
            raise _Truncated("record header cut off")
        op = buf[off]
        (length,) = struct.unpack_from("<Q", buf, off + 1)
        if off + 9 + length > n:
            if partial_ok:
                return
            raise _Truncated("record cut off")
        yield op, buf[off + 9 : off + 9 + length]
        off += 9 + length


def _decompress_chunk(compression: str, data: bytes, complete: bool) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        if complete:
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        try:
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except zstandard.ZstdError:
            return b""
    if compression == "lz4":
        import lz4.frame

        dec = lz4.frame.LZ4FrameDecompressor()
        try:
            return dec.decompress(data)
        except RuntimeError:
            if complete:
                raise
            return b""
    raise ValueError(f"unsupported MCAP chunk compression {compression!r}")


class _McapRecoverySource(BagSource):
    """Reads MCAP files record by record, without the summary section, up to the damage."""

    def __init__(self, path: Path, files: list[Path], open_error: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.files = files
        self.open_error = open_error
        self.recovered = True
        self.topics = {}
        self.message_count = None
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._channels: dict[int, tuple[str, str]] = {}
        self.typestore = get_typestore(Stores.EMPTY)
        self._fallback = get_typestore(Stores.ROS2_JAZZY)
        self._registered: set[str] = set()
        self.damage: list = []
        self._last_chunk = -1
        self._chunk_no = 0
        self._scan = False
        self._scan_count = 0
        # a first pass over the readable part finds the topics, their types and the count
        self._scan = True
        self._scan_count = 0
        for f in files:
            try:
                for _ in self._records_of(f):
                    pass
            except (_Truncated, OSError, ValueError, struct.error, RuntimeError):
                pass
        self._scan = False
        self.message_count = self._scan_count
        if not self.topics:
            raise BagReadError(path, f"{open_error}; sequential recovery found no channels")

    def _register_schema(self, name: str, encoding: str, data: bytes) -> None:
        if name in self._registered:
            return
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        text = data.decode("utf-8", "replace")
        try:
            if encoding == "ros2msg" and text.strip():
                self.typestore.register(get_types_from_msg(text, name))
            elif encoding == "ros2idl" and text.strip():
                sep = "=" * 80 + "\n"
                if text.startswith(f"{sep}IDL: "):
                    for part in text.split(sep)[1:]:
                        _, idl = part.split("\n", 1)
                        self.typestore.register(get_types_from_idl(idl))
                else:
                    self.typestore.register(get_types_from_idl(text))
        except Exception:  # noqa: BLE001 - a bad schema: deserialise with the Jazzy definitions
            pass
        self._registered.add(name)

    def _handle(self, op: int, content: bytes) -> RawMessage | None:
        if op == _OP_SCHEMA:
            (sid,) = struct.unpack_from("<H", content, 0)
            name, off = _mcap_str(content, 2)
            enc, off = _mcap_str(content, off)
            (n,) = struct.unpack_from("<I", content, off)
            data = bytes(content[off + 4 : off + 4 + n])
            self._schemas[sid] = (name, enc, data)
            self._register_schema(name, enc, data)
        elif op == _OP_CHANNEL:
            cid, sid = struct.unpack_from("<HH", content, 0)
            topic, off = _mcap_str(content, 4)
            name = self._schemas.get(sid, ("", "", b""))[0]
            self._channels[cid] = (topic, name)
            if name:
                self.topics.setdefault(topic, name)
        elif op == _OP_MESSAGE:
            cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", content, 0)
            ch = self._channels.get(cid)
            if ch is None:
                return None
            if self._scan:
                self._scan_count += 1
                return None
            return RawMessage(ch[0], ch[1], log_time, bytes(content[22:]))
        return None

    def _records_of(self, f: Path) -> Iterator[RawMessage]:
        with open(f, "rb") as fh:
            try:
                data: Any = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
            except ValueError:  # empty file
                data = b""
        if data[: len(_MCAP_MAGIC)] != _MCAP_MAGIC:
            raise _Truncated(f"{f.name}: not an MCAP file (bad magic)")
        body = memoryview(data)[len(_MCAP_MAGIC) :]
        self._chunk_no = 0
        off, n = 0, len(body)
        while off < n:
            if off + 9 > n:
                raise _Truncated(f"{f.name}: cut off in a record header at byte {off + 8}")
            op = body[off]
            (length,) = struct.unpack_from("<Q", body, off + 1)
            end = off + 9 + length
            complete = end <= n
            content = body[off + 9 : min(end, n)]
            if op == _OP_CHUNK:
                if len(content) < 8 * 3 + 4 + 4:
                    raise _Truncated(f"{f.name}: chunk header cut off at byte {off + 8}")
                damage = self._chunk_damage(f, off + 8, bytes(content)) if complete else None
                if damage is not None:  # skipped whole, its messages are reported, not replayed
                    off = end
                    continue
                comp, coff = _mcap_str(content, 28)
                (rec_len,) = struct.unpack_from("<Q", content, coff)
                records = content[coff + 8 : coff + 8 + rec_len]
                inner = _decompress_chunk(comp, records, complete)
                for iop, icontent in _iter_records(inner, partial_ok=not complete):
                    msg = self._handle(iop, icontent)
                    if msg is not None:
                        yield msg
                if not complete:
                    raise _Truncated(f"{f.name}: cut off inside a chunk at byte {n + 8} (of {end + 8})")
            else:
                if not complete:
                    raise _Truncated(f"{f.name}: cut off inside a record at byte {n + 8}")
                if op in (_OP_FOOTER,):
                    return
                if op == _OP_MESSAGE_INDEX and self.damage and self.damage[-1].offset == self._last_chunk:
                    cid, nbytes = struct.unpack_from("<HI", content, 0)
                    topic = self._channels.get(cid, (f"channel {cid}", ""))[0]
                    lost = self.damage[-1].messages
                    lost[topic] = lost.get(topic, 0) + nbytes // 16
                msg = self._handle(op, content)
                if msg is not None:
                    yield msg
            off = end
        raise _Truncated(f"{f.name}: no footer (file not finalised)")

    def _chunk_damage(self, f: Path, offset: int, content: bytes) -> Any:
        """The ChunkDamage of a complete chunk record (recorded once, while reading), or None."""
        from .bags.mcap_check import ChunkDamage, chunk_problem, parse_chunk

        self._last_chunk = offset
        self._chunk_no += 1
        try:
            problem = chunk_problem(parse_chunk(content))
        except Exception as e:  # noqa: BLE001 - an unparsable chunk header is damage too
            problem = (f"chunk record unreadable ({type(e).__name__}: {e})", None, None)
        if problem is None:
            return None
        damage = ChunkDamage(f, self._chunk_no - 1, offset, *problem)
        if not self._scan:
            self.damage.append(damage)
        return damage

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[RawMessage]:
        wanted = set(topics) if topics is not None else None
        for f in self.files:
            try:
                for m in self._records_of(f):
                    self.messages_read += 1
                    self.last_time_ns = m.log_time_ns
                    if wanted is None or m.topic in wanted:
                        yield m
            except GeneratorExit:
                raise
            except (_Truncated, OSError, ValueError, struct.error, RuntimeError, ImportError) as e:
                raise BagReadError(
                    self.path, f"{self.open_error}; read sequentially up to the damage: {e}", self.messages_read, self.last_time_ns
                ) from None

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        try:
            store = self.typestore if msgtype in self.typestore.types else self._fallback
            return store.deserialize_cdr(raw, msgtype)
        except Exception as e:  # noqa: BLE001
            raise BagReadError(
                self.path, f"cannot deserialise a {msgtype} message: {type(e).__name__}: {e}", self.messages_read, self.last_time_ns
            ) from e


def _default_typestore(path: Path) -> Any:
    from rosbags.typesys import Stores, get_typestore

    if path.suffix == ".bag":
        return get_typestore(Stores.ROS1_NOETIC)
    return get_typestore(Stores.ROS2_JAZZY)


def _mcap_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == ".mcap" else []
    meta = path / "metadata.yaml"
    files: list[Path] = []
    if meta.is_file():
        try:
            import yaml

            info = yaml.safe_load(meta.read_text()) or {}
            rel = (info.get("rosbag2_bagfile_information") or {}).get("relative_file_paths") or []
            files = [path / r for r in rel if str(r).endswith(".mcap") and (path / r).is_file()]
        except Exception:  # noqa: BLE001
            files = []
    if not files:
        files = sorted(path.glob("*.mcap"))
    return files


def open_bag(path: str | Path) -> BagSource:
    """Open a bag for sequential reading: a rosbag2 directory, a single ``.mcap`` /
    ``.db3`` file or a ROS 1 ``.bag``. Bags without message definitions use the ROS 2
    Jazzy (or ROS 1 Noetic for ``.bag``) typestore. An MCAP that rosbags cannot open
    (truncated, unfinalised) is opened in sequential recovery mode (``recovered=True``).
    Raises FileNotFoundError or :class:`BagReadError`."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such bag: {str(path)!r}")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        inner = sorted(path.glob("*.mcap")) + sorted(path.glob("*.db3"))
        if len(inner) == 1:
            path = inner[0]
        elif not inner:
            raise BagReadError(path, "directory has neither metadata.yaml nor a .mcap/.db3 file: not a rosbag2 bag")
    if path.is_file() and path.suffix not in (".mcap", ".db3", ".bag"):
        raise BagReadError(path, f"unknown bag file type {path.suffix!r} (expected .mcap, .db3 or .bag)")
    reader = AnyReader([path], default_typestore=_default_typestore(path))
    try:
        reader.open()
    except Exception as e:  # noqa: BLE001
        err = f"{type(e).__name__}: {e}"
        files = _mcap_files(path)
        if files:
            return _McapRecoverySource(path, files, f"cannot open normally ({err})")
        raise BagReadError(path, err) from e
    files = _mcap_files(path)
    if files:  # rosbags reads a damaged chunk as corrupt data or fails mid-way: check first
        from .bags.mcap_check import checked_source

        try:
            checked = checked_source(path, files)
        except OSError as e:
            reader.close()
            raise BagReadError(path, f"{type(e).__name__}: {e}") from e
        except BaseException:
            reader.close()
            raise
        if checked is not None:
            reader.close()
            return checked
    return _AnyReaderSource(path, reader)


# --- topic selection ---------------------------------------------------------------------


def _peek_encodings(source: BagSource, topics: list[str], limit: int = 400) -> dict[str, str]:
    """Encoding of the first message of each Image topic in ``topics``."""
    found: dict[str, str] = {}
    if not topics:
        return found
    if isinstance(source, _AnyReaderSource):
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

    image_topics = [t for t, ty in topics.items() if ty == IMAGE_T]
    if image is None or depth is None:
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
    if camera_info is None:
        infos = [t for t, ty in topics.items() if ty == CAMERA_INFO_T]
        parent = image.rsplit("/", 1)[0] if "/" in image.strip("/") else ""
        next_to = [t for t in infos if parent and t.rsplit("/", 1)[0] == parent]
        coloured = [t for t in infos if any(k in t.lower() for k in ("color", "colour", "rgb"))]
        if next_to:
            camera_info = sorted(next_to)[0]
        elif len(infos) == 1:
            camera_info = infos[0]
        elif coloured:
            camera_info = sorted(coloured)[0]
        elif infos:
            raise ValueError(f"several camera_info topics ({', '.join(sorted(infos))}); pass --camera-info")
        else:
            raise ValueError(f"no sensor_msgs/msg/CameraInfo topic in the bag (pass --camera-info); topics: {listing}")
    return TopicSelection(image, depth, camera_info, imu, detections2d)


# --- the frame generator -------------------------------------------------------------------


@dataclass
class ReadStats:
    """Counters of a frame read: messages per role, sets synchronised, frames yielded."""

    messages: int = 0
    per_role: dict[str, int] = field(default_factory=dict)
    synced: int = 0
    yielded: int = 0
    no_camera_info: int = 0


class BagFrameReader:
    """Synchronised frames of one bag.

    >>> with BagFrameReader("bags/sample") as reader:
    ...     for frame in reader.frames():
    ...         pf = frame.prepare()

    ``frames(on_message=cb)`` also calls ``cb(raw_message)`` for every message of the bag
    in bag order (``all_topics=True``, the default when a callback is given) so a writer
    can copy the input. ``slop`` (s) / ``queue_size``: synchroniser settings. The
    camera_info of a frame is the one nearest its stamp (a frame waits at most
    ``max_pending`` frames for a camera_info at or after its stamp).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        image: str | None = None,
        depth: str | None = None,
        camera_info: str | None = None,
        imu: str | None = None,
        detections2d: str | None = None,
        slop: float = 0.02,
        queue_size: int = 30,
        max_pending: int = 3,
        imu_time_constant: float = 0.5,
        imu_to_camera: Any = None,
    ) -> None:
        self.source = open_bag(path)
        try:
            self.selection = select_topics(self.source, image, depth, camera_info, imu, detections2d)
        except Exception:
            self.source.close()
            raise
        self.slop = float(slop)
        self.queue_size = int(queue_size)
        self.max_pending = max(0, int(max_pending))
        self.imu_time_constant = imu_time_constant
        self.imu_to_camera = imu_to_camera
        self.stats = ReadStats()

    @property
    def path(self) -> Path:
        return self.source.path

    def close(self) -> None:
        self.source.close()

    def __enter__(self) -> "BagFrameReader":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def frames(
        self,
        on_message: Callable[[RawMessage], None] | None = None,
        all_topics: bool | None = None,
    ) -> Iterator[SyncedFrame]:
        """Yield :class:`SyncedFrame` s in order; raises :class:`BagReadError` after the
        last frame completed before damage."""
        from .imu_gravity import ImuGravityFilter

        sel = self.selection
        roles = sel.roles()
        sync_roles = ["image", "depth"] + (["detections2d"] if sel.detections2d else [])
        index_of = {getattr(sel, r): i for i, r in enumerate(sync_roles)}
        sync = ApproximateTimeSynchronizer(len(sync_roles), self.queue_size, self.slop)
        imu = ImuGravityFilter(self.imu_time_constant, self.imu_to_camera) if sel.imu else None
        infos: deque[tuple[int, Any]] = deque(maxlen=64)
        pending: deque[SyncedFrame] = deque()
        stats = self.stats = ReadStats()
        if all_topics is None:
            all_topics = on_message is not None
        wanted = None if all_topics else list(roles)

        def nearest_info(stamp: int) -> Any:
            if not infos:
                return None
            return min(infos, key=lambda si: abs(si[0] - stamp))[1]

        def ready() -> Iterator[SyncedFrame]:
            while pending:
                head = pending[0]
                newest = infos[-1][0] if infos else None
                if newest is not None and newest >= head.stamp_ns or len(pending) > self.max_pending:
                    pending.popleft()
                    head.camera_info = nearest_info(head.stamp_ns)
                    if head.camera_info is None:
                        stats.no_camera_info += 1
                    stats.yielded += 1
                    yield head
                else:
                    return

        error: BaseException | None = None
        try:
            for m in self.source.messages(wanted):
                stats.messages += 1
                if on_message is not None:
                    on_message(m)
                role = roles.get(m.topic)
                if role is None:
                    continue
                stats.per_role[role] = stats.per_role.get(role, 0) + 1
                msg = self.source.deserialize(m.raw, m.msgtype)
                if role == "camera_info":
                    stamp = header_stamp_ns(msg)
                    infos.append((m.log_time_ns if stamp is None else stamp, msg))
                    yield from ready()
                    continue
                if role == "imu":
                    acc = getattr(msg, "linear_acceleration", None)
                    if acc is not None:
                        imu.update((acc.x, acc.y, acc.z), header_stamp_ns(msg))  # type: ignore[union-attr]
                    continue
                out = sync.add(index_of[m.topic], msg)
                if out is None:
                    continue
                stats.synced += 1
                img = out[0]
                pending.append(
                    SyncedFrame(
                        index=stats.synced - 1,
                        stamp_ns=int(header_stamp_ns(img) or 0),
                        frame_id=str(getattr(img.header, "frame_id", "") or ""),
                        image=img,
                        depth=out[1],
                        camera_info=None,
                        detections2d=out[2] if len(out) > 2 else None,
                        up=None if imu is None else imu.up,
                        log_time_ns=m.log_time_ns,
                    )
                )
                yield from ready()
        except BagReadError as e:
            error = e
        # end of bag (or damage): every completed frame goes out
        while pending:
            head = pending.popleft()
            head.camera_info = nearest_info(head.stamp_ns)
            if head.camera_info is None:
                stats.no_camera_info += 1
            stats.yielded += 1
            yield head
        if error is not None:
            raise error


def iter_frames(path: str | Path, **kwargs: Any) -> Iterator[SyncedFrame]:
    """Shorthand: the synchronised frames of a bag (see :class:`BagFrameReader`)."""
    with BagFrameReader(path, **kwargs) as reader:
        yield from reader.frames()


# =====================================================================================
# writing
# =====================================================================================


def _fielddefs(store: Any, msgtype: str) -> list:
    return store.fielddefs[msgtype][1]


def convert_message(msg: Any, msgtype: str, store: Any) -> Any:
    """A message of ``store`` (e.g. ROS 2 Jazzy) with the field values of ``msg`` (e.g. a
    ROS 1 message of the same type): fields matched by name, case-insensitively (ROS 1
    CameraInfo ``K`` -> ``k``); fields the source lacks get defaults (``seq`` dropped)."""
    from msg_conversion.msgtypes import MsgTypes

    helper = MsgTypes("rosbags", {}, typestore=store)

    def conv(value: Any, desc: Any) -> Any:
        kind = int(desc[0])
        if kind == 1:  # base
            base = desc[1][0]
            if base in ("string", "wstring"):
                return str(value)
            if base == "bool":
                return bool(value)
            if base.startswith("float"):
                return float(value)
            return int(value)
        if kind == 2:  # nested message
            return build(value, desc[1])
        sub = desc[1][0]
        if int(sub[0]) == 1 and sub[1][0] not in ("string", "wstring"):
            dt = {"float32": np.float32, "float64": np.float64, "bool": np.bool_}.get(sub[1][0])
            arr = np.asarray(value)
            if dt is None:
                dt = helper._default(desc).dtype if kind == 3 else np.asarray(helper._default((4, (sub, 0)))).dtype
            return np.asarray(arr, dtype=dt).reshape(-1)
        return [conv(v, sub) for v in value]

    def build(src: Any, typ: str) -> Any:
        cls = store.types[typ]
        kwargs = {}
        for name, desc in _fielddefs(store, typ):
            value = None
            for cand in (name, name.upper(), name.lower()):
                if hasattr(src, cand):
                    value = getattr(src, cand)
                    break
            else:
                if typ == "builtin_interfaces/msg/Time" and hasattr(src, "secs"):
                    value = {"sec": src.secs, "nanosec": src.nsecs}[name]
            kwargs[name] = helper._default(desc) if value is None else conv(value, desc)
        return cls(**kwargs)

    return build(msg, msgtype)


def write_rgbd_bag(
    path: str | Path,
    frames: Iterable[tuple[int, np.ndarray, np.ndarray, np.ndarray]],
    *,
    storage: str = "mcap",
    image_topic: str = "/camera/color/image_raw",
    depth_topic: str = "/camera/depth/image_raw",
    info_topic: str = "/camera/color/camera_info",
    color_encoding: str = "rgb8",
    depth_encoding: str = "16UC1",
    frame_id: str = "camera_color_optical_frame",
    depth_offset_ns: int = 0,
) -> Path:
    """Write ``(stamp_ns, rgb, depth_m, K)`` frames as a bag: colour image, depth image
    (stamp + ``depth_offset_ns``) and camera_info per frame, log time = stamp.

    ``storage``: ``'mcap'`` or ``'sqlite3'`` (rosbag2 directory ``path``) or ``'ros1'``
    (ROS 1 ``.bag`` file ``path``). For tests, tools and examples.
    """
    from msg_conversion.camera_info import K_to_camera_info
    from msg_conversion.image import depth_to_image, numpy_to_image
    from msg_conversion.msgtypes import rosbags_types

    path = Path(path)
    T = rosbags_types()
    store = T.typestore
    if color_encoding.startswith("bgr"):
        def colour(rgb: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(rgb[..., ::-1])
    else:
        def colour(rgb: np.ndarray) -> np.ndarray:
            return rgb

    def messages() -> Iterator[tuple[str, str, int, Any]]:
        for stamp, rgb, depth, K in frames:
            h, w = rgb.shape[:2]
            yield image_topic, IMAGE_T, stamp, numpy_to_image(colour(rgb), color_encoding, T, stamp, frame_id)
            dstamp = stamp + depth_offset_ns
            yield depth_topic, IMAGE_T, dstamp, depth_to_image(depth, T, depth_encoding, dstamp, frame_id)
            yield info_topic, CAMERA_INFO_T, stamp, K_to_camera_info(K, w, h, T, stamp, frame_id)

    if storage == "ros1":
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.typesys import Stores, get_typestore

        ros1 = get_typestore(Stores.ROS1_NOETIC)
        with Writer1(path) as w:
            conns: dict[str, Any] = {}
            for topic, typ, t, msg in messages():
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, typ, typestore=ros1)
                w.write(conns[topic], t, ros1.serialize_ros1(convert_message(msg, typ, ros1), typ))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
    if plugin is None:
        raise ValueError(f"storage must be 'mcap', 'sqlite3' or 'ros1', got {storage!r}")
    with Writer(path, version=8, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ, t, msg in messages():
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=store)
            w.write(conns[topic], t, store.serialize_cdr(msg, typ))
    return path


def __getattr__(name: str) -> Any:
    # OutputBag moved to shape_detector.bags.output, which imports this module
    if name == "OutputBag":
        from .bags.output import OutputBag

        return OutputBag
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(topic, log_time_ns, message)`` of a bag (deserialised), for tests and tools."""
    with open_bag(path) as src:
        for m in src.messages(topics):
            yield m.topic, m.log_time_ns, src.deserialize(m.raw, m.msgtype)


__all__ = [
    "BagFrameReader",
    "BagReadError",
    "BagSource",
    "DETECTIONS_TOPIC",
    "FrameError",
    "MARKERS_TOPIC",
    "OutputBag",
    "PreparedFrame",
    "RawMessage",
    "SyncedFrame",
    "TopicSelection",
    "convert_message",
    "iter_frames",
    "open_bag",
    "prepare_frame",
    "read_messages",
    "select_topics",
    "write_rgbd_bag",
]
