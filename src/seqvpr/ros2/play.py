"""``seqvpr play``: a bag's camera topic (and its position topic) published live over DDS at the recorded rate, as
``ros2 bag play`` does, so a node can be tried with no robot. A ROS 2 bag's messages go out as the very bytes it
holds; a ROS 1 bag's are re-encoded as their ROS 2 messages."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from seqvpr.data.loaders.rosbag import IMAGE_TYPES, BagTopics, open_bag, position_connection, topic_connection
from seqvpr.data.traversal import parse_frame_range
from seqvpr.errors import SettingError
from seqvpr.progress import ProgressFactory
from seqvpr.ros2.dds import EVERY_SAMPLE, Bus, wait_for_match
from seqvpr.ros2.messages import encode, outgoing

#: seconds of position fixes published before the first camera frame of a ``--frames`` range
MIN_RATE, MAX_RATE = 1e-3, 1e3  # times the recorded pace: an hour's drive in 3.6 s at most, 1,000 h at least
FIX_LEAD = 1.0
#: seconds between a subscriber matching and the first frame
SETTLE = 0.5


@dataclass(frozen=True)
class Played:
    """What a play sent: camera frames, position fixes, the topics, the seconds it took, whether a subscriber to
    the camera topic was matched before the first frame."""

    frames: int
    fixes: int
    camera_topic: str
    position_topic: str | None
    seconds: float
    matched: bool


def play_bag(bag: str | Path, topics: BagTopics, bus: Bus, rate: float = 1.0, frames: str | None = None,
             wait: float = 2.0, progress: ProgressFactory | None = None) -> Played:
    """Publish the camera frames ``frames`` (``START:STOP`` of its camera messages in recorded order) of ``bag``,
    and its position fixes over the same time (from ``FIX_LEAD`` s before the first), at ``rate`` x the recorded
    pace; wait up to ``wait`` s for a subscriber first. Every message goes out reliably; the call returns once
    subscribers acknowledged them."""
    if not MIN_RATE <= rate <= MAX_RATE:
        raise SettingError(f"{{rate}} must be from {MIN_RATE:g} to {MAX_RATE:g} times the recorded pace, got {rate}")
    path = Path(bag)
    with open_bag(path) as reader:
        camera = topic_connection(reader, IMAGE_TYPES, topics.image, path, "image")
        position = position_connection(reader, topics, path)
        times = [t for _, t, _ in reader.messages(connections=[camera])]
        start, stop = _frame_span(times, frames, path)
        advance = progress(stop - start, "play") if progress is not None else None
        writers = {c.topic: bus.writer(c.topic, c.msgtype, EVERY_SAMPLE) for c in (camera, position) if c}
        matched = wait_for_match(writers[camera.topic], wait) if wait > 0 else False
        if matched:  # the subscriber's side of discovery completes a moment later: frames before it come in a burst
            time.sleep(SETTLE)
        began, first, sent = time.monotonic(), times[start], {"frames": 0, "fixes": 0}
        # fixes from FIX_LEAD s before the first frame to the next frame left out (the bag's ends where it ends)
        low = first - int(FIX_LEAD * 1e9) if start > 0 else -1
        high = times[stop] - 1 if stop < len(times) else float("inf")
        index = -1
        for connection, stamp, raw in reader.messages(connections=[c for c in (camera, position) if c]):
            is_camera = connection.topic == camera.topic
            index += is_camera
            if (is_camera and not start <= index < stop) or not low <= stamp <= high:
                continue
            _sleep_until(began + max(stamp - first, 0) / 1e9 / rate)
            data = bytes(raw) if reader.is2 else encode(reader.deserialize(raw, connection.msgtype), connection.msgtype)
            writers[connection.topic].write(outgoing(connection.msgtype, data=data))
            sent["frames" if is_camera else "fixes"] += 1
            if is_camera and advance is not None:
                advance(1)
        _wait_for_acks(writers.values())
    return Played(sent["frames"], sent["fixes"], camera.topic, position.topic if position else None,
                  time.monotonic() - began, matched)


def _frame_span(times: list[int], frames: str | None, path: Path) -> tuple[int, int]:
    """The half-open range of camera messages ``frames`` names (all of them when None); one line if it is empty."""
    start, stop = parse_frame_range(frames)
    span = range(len(times))[slice(start, stop)]
    if not len(span) or span.step != 1:
        raise SettingError(f"{{frames}} {frames}: {path} has {len(times)} camera frames; that range holds none")
    return span.start, span.stop


def _sleep_until(deadline: float) -> None:
    left = deadline - time.monotonic()
    if left > 0:
        time.sleep(left)


def _wait_for_acks(writers, seconds: float = 30.0) -> None:
    """Let reliable subscribers receive what was written before the participant goes (best effort ones need not)."""
    from cyclonedds.util import duration

    for writer in writers:
        writer.wait_for_acks(duration(seconds=seconds))
