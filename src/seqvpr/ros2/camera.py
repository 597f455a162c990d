"""What the node reads and publishes, as plain functions of messages and estimates: camera messages to images, the
time-gap rule that restarts the localiser, and an estimate as a ROS 2 pose and diagnostic status."""

from __future__ import annotations

import io
import math
from collections import deque
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
from PIL import Image

from seqvpr.data.images import decode_image, raw_pixels
from seqvpr.data.traversal import GAP_FACTOR
from seqvpr.errors import SeqvprError
from seqvpr.data.geo import LOCAL, parse_crs
from seqvpr.ros2.messages import COMPRESSED, IMAGE, ODOMETRY, POSE, STATUS, message

#: the variance of what a 2-D map does not say (height, roll, pitch; heading where the track gives none)
UNKNOWN_VARIANCE = 1e6
#: the standard deviation of a localised estimate's heading, radians (the track's direction at the matched frame)
HEADING_SIGMA = 0.2
#: diagnostic_msgs/DiagnosticStatus levels by localiser state
LEVELS = {"localised": 0, "warming up": 1, "uncertain": 1, "lost": 2}
WARN = 1


def camera_type(topic: str, given: str | None = None) -> str:
    """The message type of a camera topic: ``given`` (raw or compressed), else image_transport's convention: a
    topic ending in ``/compressed`` carries CompressedImage, any other Image."""
    if given is not None:
        return COMPRESSED if given == "compressed" else IMAGE
    return COMPRESSED if topic.rstrip("/").endswith("/compressed") else IMAGE


def stamp_seconds(value: Any) -> float:
    """A header's stamp in seconds."""
    return float(value.header.stamp.sec) + 1e-9 * float(value.header.stamp.nanosec)


def stamp_text(value: Any) -> str:
    """A header's stamp exactly, ``SEC.NANOSEC`` (how a bag's frames are named)."""
    return f"{int(value.header.stamp.sec)}.{int(value.header.stamp.nanosec):09d}"


def camera_image(value: Any, msgtype: str) -> Image.Image:
    """The 8-bit RGB image of a camera message, decoded as ``seqvpr localize`` decodes the same message in a bag
    (a raw Image's pixels as they are, a CompressedImage's bytes by PIL); a malformed one is one line."""
    where = f"frame {stamp_text(value)}"
    if msgtype == COMPRESSED:
        data = np.ascontiguousarray(value.data).tobytes()
        if not data:
            raise SeqvprError(f"{where}: an empty compressed image")
        return decode_image(io.BytesIO(data), where, "RGB", f"{value.format or 'compressed'} image")
    pixels = raw_pixels(str(value.encoding), int(value.height), int(value.width), int(value.step),
                        bool(value.is_bigendian), value.data, where)
    return Image.fromarray(pixels).convert("RGB")


@dataclass
class TimeGaps:
    """The causal form of a recording's segment rule (``time_gap_segments``): a frame starts a new segment when its
    stamp goes back or steps more than ``GAP_FACTOR`` x the median step so far (over the last ``window`` steps)."""

    window: int = 1000
    last: float | None = None
    steps: deque = field(default_factory=deque)

    def starts_segment(self, stamp: float) -> bool:
        """Whether the frame stamped ``stamp`` begins a new segment (the localiser restarts there)."""
        previous, self.last = self.last, stamp
        if previous is None:
            return False
        step = stamp - previous
        self.steps.append(step)
        while len(self.steps) > self.window:
            self.steps.popleft()
        median = float(np.median(self.steps))
        return step < 0 or (median > 0 and step > GAP_FACTOR * median)

    def state(self) -> dict[str, Any]:
        return {"last": self.last, "steps": list(self.steps)}

    def load(self, saved: dict[str, Any]) -> None:
        last, steps = saved.get("last"), saved.get("steps", [])
        if not (last is None or isinstance(last, (int, float))) or not all(isinstance(s, (int, float)) for s in steps):
            raise SeqvprError("the saved state's time-gap record is malformed")
        self.last, self.steps = last, deque(float(s) for s in steps)


@dataclass(frozen=True)
class Track:
    """Where the map's frames are, for poses: positions [N, 2] in the map's ``crs``, the direction of travel at
    each frame (radians from +x, counter-clockwise; NaN where a segment has one frame) and the median spacing of
    consecutive frames (the position's standard deviation when localised)."""

    positions: np.ndarray
    headings: np.ndarray
    spacing: float
    crs: str | None

    @classmethod
    def of(cls, positions: np.ndarray | None, segments: np.ndarray, crs: str | None) -> Track | None:
        """The track of a map's frames (None when the map holds no positions: no pose can be published)."""
        if positions is None:
            return None
        xy = np.asarray(positions, np.float64)[:, :2]
        seg = np.asarray(segments)
        headings = np.full(len(xy), np.nan)
        steps = []
        for label in np.unique(seg):
            rows = np.flatnonzero(seg == label)
            if len(rows) < 2:
                continue
            ahead = np.gradient(xy[rows], axis=0)  # central differences inside, one-sided at the ends
            headings[rows] = np.arctan2(ahead[:, 1], ahead[:, 0])
            steps.append(np.linalg.norm(np.diff(xy[rows], axis=0), axis=1))
        spacing = float(np.median(np.concatenate(steps))) if steps else 1.0
        return cls(xy, headings, spacing if spacing > 0 else 1.0, crs)


def pose_covariance(spacing: float, misses: int, heading_known: bool) -> list[float]:
    """The 6 x 6 covariance (x, y, z, roll, pitch, yaw; row-major): x and y of standard deviation ``spacing`` when
    localised, ``(1 + misses)`` times that after ``misses`` frames below the threshold; yaw ``HEADING_SIGMA`` as
    much; what a 2-D map does not say ``UNKNOWN_VARIANCE``."""
    grow = 1.0 + misses
    cov = np.zeros((6, 6))
    cov[0, 0] = cov[1, 1] = (spacing * grow) ** 2
    cov[2, 2] = cov[3, 3] = cov[4, 4] = UNKNOWN_VARIANCE
    cov[5, 5] = (HEADING_SIGMA * grow) ** 2 if heading_known else UNKNOWN_VARIANCE
    return cov.ravel().tolist()


def header(stamp: Any, frame_id: str):
    """A std_msgs/Header with the camera frame's stamp."""
    return message("std_msgs/msg/Header", stamp=message("builtin_interfaces/msg/Time", sec=int(stamp.sec),
                                                        nanosec=int(stamp.nanosec)), frame_id=frame_id)


_ZERO = SimpleNamespace(sec=0, nanosec=0)  # the stamp of what is of no one moment (the route)


def route_of(track: Track, frame_id: str):
    """The map's route as a nav_msgs/Path: one pose a map frame, facing the direction of travel there (stamp 0:
    the route is not of any one moment)."""
    poses = []
    for (x, y), yaw in zip(track.positions.tolist(), track.headings.tolist()):
        half = yaw / 2 if math.isfinite(yaw) else 0.0
        pose = message("geometry_msgs/msg/Pose", position=message("geometry_msgs/msg/Point", x=float(x), y=float(y),
                                                                  z=0.0),
                       orientation=message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(half),
                                           w=math.cos(half)))
        poses.append(message("geometry_msgs/msg/PoseStamped", header=header(_ZERO, frame_id), pose=pose))
    return message("nav_msgs/msg/Path", header=header(_ZERO, frame_id), poses=poses)


def pose_of(estimate, misses: int, track: Track, stamp: Any, frame_id: str):
    """The PoseWithCovarianceStamped of an estimate: the matched map frame (the localised one; the best one while
    uncertain, its covariance grown); None while warming up or lost, where nothing can be acted on."""
    if estimate.status not in ("localised", "uncertain") or estimate.best is None:
        return None
    row = estimate.index if estimate.status == "localised" else estimate.best
    x, y = (float(v) for v in track.positions[row])
    yaw = float(track.headings[row])
    known = math.isfinite(yaw)
    half = yaw / 2 if known else 0.0
    pose = message("geometry_msgs/msg/Pose",
                   position=message("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
                   orientation=message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(half),
                                       w=math.cos(half)))
    covariance = np.array(pose_covariance(track.spacing, misses if estimate.status == "uncertain" else 0, known))
    return message(POSE, header=header(stamp, frame_id),
                   pose=message("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=covariance))


def status_of(values: dict[str, Any], level: int, text: str, stamp: Any, frame_id: str, hardware_id: str,
              name: str = "seqvpr localiser"):
    """A DiagnosticArray of one DiagnosticStatus named ``name``: ``level``, ``text`` and ``values`` (key-value
    texts; floats written exactly, ``repr``)."""
    pairs = [message("diagnostic_msgs/msg/KeyValue", key=k, value=_text(v)) for k, v in values.items()]
    status = message("diagnostic_msgs/msg/DiagnosticStatus", level=level, name=name, message=text,
                     hardware_id=hardware_id, values=pairs)
    return message(STATUS, header=header(stamp, frame_id), status=[status])


def _text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def status_values(status: Any) -> dict[str, str]:
    """The key-value texts of a status message (the first DiagnosticStatus), for a reader of ``/seqvpr/status``."""
    return {kv.key: kv.value for kv in status.status[0].values}


def fix_in_map(value: Any, msgtype: str | None, crs: str | None) -> tuple[float, float] | None:
    """A position fix in the map's coordinates: a NavSatFix's latitude and longitude in the map's UTM zone, an
    Odometry's x, y on a local map; None where the two do not meet (or the fix is not finite)."""
    if msgtype == ODOMETRY:
        point = value.pose.pose.position
        return (float(point.x), float(point.y)) if crs in (None, LOCAL) else None
    zone = parse_crs(crs)
    lat, lon = float(value.latitude), float(value.longitude)
    if zone is None or not (math.isfinite(lat) and math.isfinite(lon) and -80 <= lat <= 84 and -180 <= lon <= 180):
        return None
    import utm

    easting, northing, _, _ = utm.from_latlon(lat, lon, force_zone_number=zone[0], force_northern=zone[1])
    return float(easting), float(northing)
