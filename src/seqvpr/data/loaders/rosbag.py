"""Robot recordings: ROS 1 ``.bag`` files and ROS 2 bags (a folder with ``metadata.yaml`` and ``.db3``/``.mcap``
files), read with the pure-Python ``rosbags`` package.

A source is ``BAG[:/image/topic][?gps=/fix|odom=/odom][&tolerance=S]`` (the CLI's ``--topic``, ``--gps-topic``,
``--odom-topic`` and ``--stamp-tolerance`` write it): the frames of that ``sensor_msgs/Image`` or ``CompressedImage``
topic (the bag's only image topic when none is named), stamped by their headers. Positions come from the named
``NavSatFix`` topic (to UTM metres, ``crs`` its zone) or ``nav_msgs/Odometry`` topic (x, y, ``crs`` ``local``),
else the bag's NavSatFix topic, else its Odometry topic, matched to each frame by the nearest stamp within
``tolerance`` seconds (frames without one are left out). Segments break at time gaps.

Loading scans the messages and decodes no pixels: each frame's bytes are stored as an image file in a
content-keyed cache (``frames_root``: a CompressedImage's own bytes, a raw Image as a fast lossless PNG), so a
descriptor decodes a frame only when it reads it (``seqvpr.data.images.read_image``). The frames are named by bag,
topic and stamp (``run1.bag:/camera/image_raw@1700000000.123456789``), never by their cache files.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.data.geo import LOCAL, latlon_to_utm
from seqvpr.data.traversal import Traversal, time_gap_segments
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.io import check_output_apart

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
GPS_TYPE, ODOM_TYPE = "sensor_msgs/msg/NavSatFix", "nav_msgs/msg/Odometry"
TOLERANCE = 0.5  # seconds between a frame and the position fix it takes
FRAMES_KIND = "bag-frames"  # the cache folder (seqvpr.cache) of bags' frame files


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
    """What a bag's topics give, in stamp order: frame stamps (s, and as ``SEC.NANOSEC`` texts) and the cached
    file of each frame; position fixes (stamps, [n, 2] m) in ``crs``; and the topics read."""

    stamps: np.ndarray
    stamp_texts: list[str]
    files: list[Path]
    fix_stamps: np.ndarray | None
    fixes: np.ndarray | None
    crs: str | None
    camera_topic: str
    position_topic: str | None


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
    """The bag's image topic as a traversal of cached frame files (no pixel decoded) named ``BAG:TOPIC@STAMP``, with
    header timestamps, positions and their ``crs`` and time-gap segments; what was read (the topics, the frames left
    out) goes to the ``seqvpr`` logger, which the command line prints."""
    path = Path(path)
    recording = read_recording(path, topics, Path(frames_dir) if frames_dir is not None else frames_root())
    keep, positions = _positions(recording, topics.tolerance, path)
    stamps = recording.stamps[keep]
    names = unique_names([f"{path}:{recording.camera_topic}@{recording.stamp_texts[i]}" for i in keep], path)
    _log_reading(bag_source(path, topics), recording.camera_topic,
                 recording.position_topic if positions is not None else None, len(recording.stamps) - len(keep),
                 topics.tolerance)
    return Traversal(f"{path.stem}{topics.image or ''}".replace("/", "_"), np.asarray(keep, np.int64),
                     time_gap_segments(stamps), None, tuple(recording.files[i] for i in keep), positions, stamps,
                     source=str(path), names=names, crs=recording.crs)


def unique_names(names: list[str], path: Path) -> tuple[str, ...]:
    """Frame names by stamp, kept unique where stamps repeat (a camera driver that stamps 0, or twice alike): the
    second and later frames of one stamp get ``#2``, ``#3``... in recorded order, and one warning counts them."""
    seen: dict[str, int] = {}
    unique = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        unique.append(name if seen[name] == 1 else f"{name}#{seen[name]}")
    repeated = len(names) - len(seen)
    if repeated:
        from seqvpr.progress import LOGGER

        LOGGER.warning(f"{path}: {repeated} camera frames repeat another frame's header stamp (zero or duplicate "
                       "stamps): named by stamp and #N; their time gaps, and the fixes they take, are not to be trusted")
    return tuple(unique)


def _log_reading(source: str, camera_topic: str, position_topic: str | None, without_fix: int,
                 tolerance: float) -> None:
    """What loading a bag found, one line each: the camera topic, the position topic, the frames left out."""
    from seqvpr.progress import LOGGER

    LOGGER.info(f"{source}: camera topic {camera_topic}")
    LOGGER.info(f"{source}: position topic {position_topic or 'none'}")
    LOGGER.info(f"{source}: {without_fix} frames without a position fix within {tolerance:g} s (left out)")


@contextlib.contextmanager
def open_bag(path: Path) -> Iterator[Any]:
    """``with open_bag(path) as reader:`` rosbags' reader over a bag, the one boundary every bag is read through:
    what the reader (or the YAML of a ROS 2 bag's metadata) raises on a damaged, truncated or missing bag becomes one
    line naming it; seqvpr's own errors (a topic that is not there) pass as they are."""
    from rosbags.highlevel import AnyReader

    try:
        with AnyReader([path]) as reader:
            yield reader
    except SeqvprError:
        raise
    except Exception as error:  # rosbags' own errors (ReaderError...), YAML's, and the file system's
        if isinstance(error, (OSError, ValueError, KeyError, EOFError, IndexError, AssertionError, MemoryError,
                              struct.error)) or \
                type(error).__module__.startswith(("rosbags", "yaml", "ruamel", "lz4", "zstandard", "zlib")):
            detail = " ".join(str(error).split())[:300] or type(error).__name__
            raise SeqvprError(f"{path}: not a readable bag ({type(error).__name__}: {detail})") from None
        raise


def read_recording(path: Path, topics: BagTopics = BagTopics(), folder: Path | None = None) -> Recording:
    """Every frame of the image topic (stored in ``folder``, by default ``frames_root()``) and every fix of the
    position topic, in stamp order."""
    from seqvpr.cache import writable_folder

    folder = frames_root() if folder is None else folder
    chosen = os.environ.get("SEQVPR_BAG_FRAMES", "").strip()
    variable = "SEQVPR_BAG_FRAMES" if chosen and folder == Path(chosen).expanduser() else "SEQVPR_CACHE"
    check_output_apart(folder, [path], f"the bag frame cache (${variable})")
    folder = writable_folder(folder, variable)
    with open_bag(path) as reader:
        image = topic_connection(reader, IMAGE_TYPES, topics.image, path, "image")
        frames = [(_stamp(m), _stamp_text(m), _frame_file(m, folder, path)) for m in _messages(reader, image)]
        position = position_connection(reader, topics, path)
        fixes = [(_stamp(m), _fix(m), _fix_fault(m)) for m in _messages(reader, position)] if position else []
    if not frames:
        raise SeqvprError(f"{path}: topic {image.topic} holds no frames")
    frames.sort(key=lambda f: f[0])
    fixes = usable_fixes(sorted(fixes, key=lambda f: f[0]), f"{path}: {position.topic}" if position else str(path))
    metres, crs = _metres(np.array([f[1] for f in fixes]), position, path) if fixes else (None, None)
    return Recording(np.array([f[0] for f in frames]), [f[1] for f in frames], [f[2] for f in frames],
                     np.array([f[0] for f in fixes]) if fixes else None, metres, crs, image.topic,
                     position.topic if position else None)


def topic_connection(reader, types: tuple[str, ...], topic: str | None, path: Path, what: str):
    """The connection of ``topic`` (checked to be of ``types``), or the bag's only one of those types."""
    found = [c for c in reader.connections if c.msgtype in types and (topic is None or c.topic == topic)]
    names = sorted({c.topic for c in reader.connections if c.msgtype in types})
    if topic is not None and not found:
        raise SeqvprError(f"{path}: no {what} topic {topic} (its {what} topics: {', '.join(names) or 'none'})")
    if len({c.topic for c in found}) != 1:
        listing = ", ".join(names) or "none"
        raise SettingError(f"{path}: name the {what} topic with {{topic}} (its {what} topics: {listing})")
    return found[0]


def position_connection(reader, topics: BagTopics, path: Path):
    """The named gps or odom topic (checked), else the bag's NavSatFix topic, else its Odometry topic, else None."""
    if topics.gps:
        return topic_connection(reader, (GPS_TYPE,), topics.gps, path, "NavSatFix")
    if topics.odom:
        return topic_connection(reader, (ODOM_TYPE,), topics.odom, path, "Odometry")
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


def _stamp_text(message) -> str:
    """The header stamp exactly, ``SEC.NANOSEC`` (nine digits): a frame's name, which a float would round."""
    return f"{int(message.header.stamp.sec)}.{int(message.header.stamp.nanosec):09d}"


def _fix(message) -> np.ndarray:
    """(latitude, longitude) of a NavSatFix, or (x, y) of an Odometry pose."""
    if hasattr(message, "latitude"):
        return np.array([message.latitude, message.longitude], dtype=np.float64)
    position = message.pose.pose.position
    return np.array([position.x, position.y], dtype=np.float64)


EARTH_M = 4.1e7  # an odometry position farther than the Earth's circumference from its origin is no position


def _fix_fault(message) -> str | None:
    """Why a position message is no usable fix (None: it is one): a NavSatFix whose status says no fix, or whose
    latitude/longitude are not on the globe; an odometry pose that is not finite or beyond the planet."""
    values = _fix(message)
    if not np.all(np.isfinite(values)):
        return "not finite"
    if hasattr(message, "latitude"):
        if int(message.status.status) < 0:  # STATUS_NO_FIX
            return "status: no fix"
        if not (-90.0 <= values[0] <= 90.0 and -180.0 <= values[1] <= 180.0):
            return "not on the globe"
    elif np.abs(values).max() > EARTH_M:
        return "beyond the planet"
    return None


def usable_fixes(fixes: list[tuple[float, np.ndarray, str | None]], where: str) -> list[tuple[float, np.ndarray]]:
    """The fixes (stamp, values, fault) without a fault, as (stamp, values); those left out counted by reason in one
    warning naming ``where`` (a frame then takes the nearest usable fix, or none, as frames without one do)."""
    faults: dict[str, int] = {}
    for _, _, fault in fixes:
        if fault is not None:
            faults[fault] = faults.get(fault, 0) + 1
    if faults:
        from seqvpr.progress import LOGGER

        LOGGER.warning(f"{where}: {sum(faults.values())} position fixes left out ("
                       + ", ".join(f"{count} {fault}" for fault, count in sorted(faults.items())) + ")")
    return [(stamp, values) for stamp, values, fault in fixes if fault is None]


def _metres(values: np.ndarray, connection, path: Path) -> tuple[np.ndarray, str]:
    """Fixes in metres and their ``crs``: NavSatFix latitude/longitude to UTM (the first fix's zone), odometry as
    it is (``local``)."""
    if connection.msgtype != GPS_TYPE:
        return values, LOCAL
    return latlon_to_utm(values[:, 0], values[:, 1], f"{path}: {connection.topic}")


def _frame_file(message, folder: Path, path: Path) -> Path:
    """The cached image file of a frame message, written if absent: a CompressedImage's bytes as they are, a raw
    Image as a fast lossless PNG; named by the sha256 of the message's bytes and format, so any bag holding the
    same frame finds it."""
    compressed = hasattr(message, "format")
    kind = (str(message.format) if compressed else
            f"{message.encoding}|{message.height}|{message.width}|{message.step}|{message.is_bigendian}")
    digest = hashlib.sha256(kind.encode() + b"\0")
    digest.update(memoryview(np.ascontiguousarray(message.data)))
    key = digest.hexdigest()
    file = folder / key[:2] / f"{key}{_suffix(message.format) if compressed else '.png'}"
    if not file.is_file():
        _write_frame(file, message, compressed, path)
    return file


def _suffix(image_format: str) -> str:
    """The file suffix of a CompressedImage ``format`` (``jpeg``, ``png``, ``bgr8; jpeg compressed bgr8``, ...)."""
    text = image_format.lower()
    return ".png" if "png" in text else ".jpg" if ("jpeg" in text or "jpg" in text) else ".img"


def _write_frame(file: Path, message, compressed: bool, path: Path) -> None:
    """Write one frame's file atomically (a half-written file never carries the name)."""
    from PIL import Image

    from seqvpr.data.images import raw_pixels
    from seqvpr.io import atomic_write

    with atomic_write(file, "wb") as handle:
        if compressed:
            handle.write(memoryview(np.ascontiguousarray(message.data)))
        else:
            pixels = raw_pixels(message.encoding, int(message.height), int(message.width), int(message.step),
                                bool(message.is_bigendian), message.data, str(path))
            Image.fromarray(pixels).save(handle, format="PNG", compress_level=1)


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


def frames_root() -> Path:
    """The folder of bags' frame files: ``$SEQVPR_BAG_FRAMES`` if set and non-empty, else the cache folder
    ``bag-frames`` (``seqvpr.cache``)."""
    from seqvpr.cache import cache_folder

    chosen = os.environ.get("SEQVPR_BAG_FRAMES", "").strip()  # set but empty: as unset, never the current folder
    return Path(chosen).expanduser() if chosen else cache_folder(FRAMES_KIND)
