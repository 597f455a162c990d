"""Robot recordings: ROS 1 ``.bag`` files and ROS 2 bags (a folder with ``metadata.yaml`` and ``.db3``/``.mcap``
files), read with the pure-Python ``rosbags`` package.

A source is ``BAG[:/image/topic][?gps=/fix|odom=/odom][&tolerance=S]`` (the CLI's ``--topic``, ``--gps-topic``,
``--odom-topic`` and ``--stamp-tolerance`` write it): the frames of that ``sensor_msgs/Image`` or ``CompressedImage``
topic (the bag's only image topic when none is named), stamped by their headers. Positions come from the named
``NavSatFix`` topic (to UTM metres) or ``nav_msgs/Odometry`` topic (x, y), else the bag's NavSatFix topic, else its
Odometry topic, matched to each frame by the nearest stamp within ``tolerance`` seconds (frames without one are left
out). Segments break at time gaps. The frames are decoded once into a folder of PNGs (keyed by the bag's path, size and mtime) so every
descriptor reads them as images.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
GPS_TYPE, ODOM_TYPE = "sensor_msgs/msg/NavSatFix", "nav_msgs/msg/Odometry"
TOLERANCE = 0.5  # seconds between a frame and the position fix it takes


@dataclass(frozen=True)
class BagTopics:
    """Which topics of a bag give the frames and the positions, and how near in time a fix must be to its frame."""

    image: str | None = None
    gps: str | None = None
    odom: str | None = None
    tolerance: float = TOLERANCE


def is_rosbag(path: Path) -> bool:
    """A ROS 1 bag file, or a ROS 2 bag folder (metadata.yaml) or its single ``.mcap``/``.db3`` file."""
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file())


@dataclass(frozen=True)
class Recording:
    """What a bag's topics give: frame stamps (s) and decoded images, and position fixes (stamps, [n, 2] m)."""

    stamps: np.ndarray
    images: list[np.ndarray]
    fix_stamps: np.ndarray | None
    fixes: np.ndarray | None


def parse_bag_source(text: str) -> tuple[Path, BagTopics] | None:
    """The bag and topics a source ``BAG[:/image][?gps=/fix|odom=/odom][&tolerance=S]`` names; None if not a bag."""
    base, _, query = text.partition("?")
    head, sep, image = base.partition(":/")
    path = Path(head if sep else base)
    if not is_rosbag(path):
        return None
    fields = _query_fields(text, query)
    try:
        tolerance = float(fields.get("tolerance", TOLERANCE))
    except ValueError:
        tolerance = -1.0
    if not (tolerance > 0 and np.isfinite(tolerance)):
        raise SeqvprError(f"{text}: the stamp tolerance must be a positive number of seconds, got {fields['tolerance']!r}")
    if "gps" in fields and "odom" in fields:
        raise SeqvprError(f"{text}: positions come from a gps topic or an odom topic, not both")
    return path, BagTopics("/" + image if sep else None, fields.get("gps"), fields.get("odom"), tolerance)


def _query_fields(text: str, query: str) -> dict[str, str]:
    """The ``key=value`` pairs after a bag source's ``?``; an unknown key or a pair without ``=`` is an error."""
    fields = dict(part.partition("=")[::2] for part in query.split("&")) if query else {}
    unknown = sorted(k for k in fields if k not in ("gps", "odom", "tolerance") or not fields[k])
    if unknown:
        raise SeqvprError(f"{text}: {unknown[0]!r} is not a bag option with a value (gps=TOPIC, odom=TOPIC, "
                          "tolerance=SECONDS)")
    return fields


def bag_source(path: str | Path, topics: BagTopics) -> str:
    """The source text naming ``path`` with ``topics`` (what ``parse_bag_source`` reads back)."""
    fields = [f"{k}={v}" for k, v in (("gps", topics.gps), ("odom", topics.odom)) if v]
    if topics.tolerance != TOLERANCE:
        fields.append(f"tolerance={topics.tolerance:g}")
    return f"{path}{':' + topics.image if topics.image else ''}{'?' + '&'.join(fields) if fields else ''}"


def load_rosbag(path: str | Path, topics: BagTopics = BagTopics(), frames_dir: str | Path | None = None) -> Traversal:
    """The bag's image topic as a traversal of PNG frames with header timestamps, positions and time-gap segments."""
    from seqvpr.data.loaders.dbstruct import time_gap_segments

    path = Path(path)
    recording = read_recording(path, topics)
    keep, positions = _positions(recording, topics.tolerance, path)
    folder = Path(frames_dir) if frames_dir is not None else _frames_folder(path, topics.image)
    paths = _write_frames(folder, keep, recording.images)
    stamps = recording.stamps[keep]
    return Traversal(f"{path.stem}{topics.image or ''}".replace("/", "_"), np.asarray(keep, np.int64),
                     time_gap_segments(stamps), None, paths, positions, stamps, source=str(path))


def read_recording(path: Path, topics: BagTopics = BagTopics()) -> Recording:
    """Every frame of the image topic and every fix of the position topic, in stamp order."""
    from rosbags.highlevel import AnyReader

    try:
        with AnyReader([path]) as reader:
            image = _one_topic(reader, IMAGE_TYPES, topics.image, path, "image")
            frames = [(_stamp(m), _decode(m, path)) for m in _messages(reader, image)]
            position = _position_topic(reader, topics, path)
            fixes = [(_stamp(m), _fix(m)) for m in _messages(reader, position)] if position else []
    except (OSError, ValueError, KeyError) as error:
        raise SeqvprError(f"{path}: not a readable bag ({type(error).__name__}: {error})") from None
    except Exception as error:  # rosbags' own errors (ReaderError, ...) name the problem
        if type(error).__module__.startswith("rosbags"):
            raise SeqvprError(f"{path}: not a readable bag ({type(error).__name__}: {error})") from None
        raise
    if not frames:
        raise SeqvprError(f"{path}: topic {image.topic} holds no frames")
    frames.sort(key=lambda f: f[0])
    fixes = [f for f in sorted(fixes, key=lambda f: f[0]) if np.all(np.isfinite(f[1]))]
    return Recording(np.array([f[0] for f in frames]), [f[1] for f in frames],
                     np.array([f[0] for f in fixes]) if fixes else None,
                     _metres(np.array([f[1] for f in fixes]), position, path) if fixes else None)


def _one_topic(reader, types: tuple[str, ...], topic: str | None, path: Path, what: str):
    """The connection of ``topic`` (checked to be of ``types``), or the bag's only one of those types."""
    found = [c for c in reader.connections if c.msgtype in types and (topic is None or c.topic == topic)]
    names = sorted({c.topic for c in reader.connections if c.msgtype in types})
    if topic is not None and not found:
        raise SeqvprError(f"{path}: no {what} topic {topic} (its {what} topics: {', '.join(names) or 'none'})")
    if len({c.topic for c in found}) != 1:
        listing = ", ".join(names) or "none"
        raise SeqvprError(f"{path}: name the {what} topic with --topic (its {what} topics: {listing})")
    return found[0]


def _position_topic(reader, topics: BagTopics, path: Path):
    """The named gps or odom topic (checked), else the bag's NavSatFix topic, else its Odometry topic, else None."""
    if topics.gps:
        return _one_topic(reader, (GPS_TYPE,), topics.gps, path, "NavSatFix")
    if topics.odom:
        return _one_topic(reader, (ODOM_TYPE,), topics.odom, path, "Odometry")
    for msgtype in (GPS_TYPE, ODOM_TYPE):
        found = [c for c in reader.connections if c.msgtype == msgtype]
        if found:
            return found[0]
    return None


def _messages(reader, connection):
    for conn, _, raw in reader.messages(connections=[connection]):
        yield reader.deserialize(raw, conn.msgtype)


def _stamp(message) -> float:
    return float(message.header.stamp.sec) + 1e-9 * float(message.header.stamp.nanosec)


def _fix(message) -> np.ndarray:
    """(latitude, longitude) of a NavSatFix, or (x, y) of an Odometry pose."""
    if hasattr(message, "latitude"):
        return np.array([message.latitude, message.longitude], dtype=np.float64)
    position = message.pose.pose.position
    return np.array([position.x, position.y], dtype=np.float64)


def _metres(values: np.ndarray, connection, path: Path) -> np.ndarray:
    """Fixes in metres: NavSatFix latitude/longitude to UTM (the first fix's zone), odometry as it is."""
    if connection.msgtype != GPS_TYPE:
        return values
    from seqvpr.data.loaders.image_folder import latlon_to_utm

    return latlon_to_utm(path, values[:, 0], values[:, 1])


def _decode(message, path: Path) -> np.ndarray:
    """An RGB (or gray) uint8 array from an Image (rgb8, bgr8, rgba8, bgra8, mono8, mono16) or CompressedImage."""
    if hasattr(message, "format"):
        import io

        from seqvpr.data.images import to_8bit

        with Image.open(io.BytesIO(bytes(message.data))) as image:
            return np.asarray(to_8bit(image, "RGB"))
    data, encoding = np.frombuffer(bytes(message.data), np.uint8), message.encoding
    h, w, step = int(message.height), int(message.width), int(message.step)
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2}.get(encoding)
    if channels is None:
        raise SeqvprError(f"{path}: image encoding {encoding!r} is not supported (rgb8, bgr8, rgba8, bgra8, mono8, mono16)")
    rows = data.reshape(h, step)[:, : w * channels]
    if encoding == "mono16":
        wide = rows.view(">u2" if message.is_bigendian else "<u2").reshape(h, w)
        return (wide >> 8).astype(np.uint8)
    pixels = rows.reshape(h, w, channels) if channels > 1 else rows.reshape(h, w)
    if encoding.startswith("bgr"):
        pixels = pixels[..., 2::-1]
    return np.ascontiguousarray(pixels[..., :3] if channels == 4 else pixels)


def _positions(recording: Recording, tolerance: float, path: Path) -> tuple[list[int], np.ndarray | None]:
    """Frames that have a fix within ``tolerance`` s (all frames when the bag has no positions) and their positions."""
    n = len(recording.stamps)
    if recording.fix_stamps is None:
        return list(range(n)), None
    nearest = np.clip(np.searchsorted(recording.fix_stamps, recording.stamps), 0, len(recording.fix_stamps) - 1)
    before = np.clip(nearest - 1, 0, None)
    pick = np.where(np.abs(recording.fix_stamps[before] - recording.stamps)
                    <= np.abs(recording.fix_stamps[nearest] - recording.stamps), before, nearest)
    close = np.abs(recording.fix_stamps[pick] - recording.stamps) <= tolerance
    if not close.any():
        raise SeqvprError(f"{path}: no frame has a position fix within {tolerance} s")
    keep = np.flatnonzero(close)
    return keep.tolist(), recording.fixes[pick[keep]]


def _frames_folder(path: Path, topic: str | None) -> Path:
    """Where a bag's frames are decoded: a folder keyed by the bag's path, size, mtime and topic."""
    stat = path.stat() if path.is_file() else (path / "metadata.yaml").stat()
    key = hashlib.sha256(f"{path.absolute()}|{stat.st_size}|{stat.st_mtime_ns}|{topic}".encode()).hexdigest()[:16]
    return _frames_root() / key


def _frames_root() -> Path:
    """The folder of decoded bag frames: ``$SEQVPR_BAG_FRAMES``, else ``seqvpr-bag-frames`` in the temp folder."""
    chosen = os.environ.get("SEQVPR_BAG_FRAMES", "").strip()  # set but empty: as unset, never the current folder
    return Path(chosen) if chosen else Path(tempfile.gettempdir()) / "seqvpr-bag-frames"


def _write_frames(folder: Path, keep: list[int], images: list[np.ndarray]) -> tuple[Path, ...]:
    """The kept frames as PNGs named by their place in the topic, in ``folder`` (each written once, atomically)."""
    from seqvpr.io import atomic_write

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in keep:
        file = folder / f"{i:06d}.png"
        if not file.exists():
            with atomic_write(file, "wb") as handle:
                Image.fromarray(images[i]).save(handle, format="PNG")
        paths.append(file)
    return tuple(paths)
