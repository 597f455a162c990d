"""``seqvpr node``: the online localiser as a ROS 2 participant. Camera frames come in on a topic, each goes through
the ``Localizer``, and the estimate goes out as a pose (``/seqvpr/pose``) and a diagnostic status
(``/seqvpr/status``); ``/seqvpr/reset`` restarts it.

A receiving thread takes samples as they arrive and hands them to the localiser through an ``Inbox``: by default
the newest frame waits and an older one still waiting is dropped (counted), so the node answers for the latest
frame when it falls behind; with ``keep_all`` (``--no-drop``) every frame is processed in order, as a replay must.

With loop detection (``NodeSettings.loops``, ``--loops``) each described frame also goes to a ``LoopDetector``
(``seqvpr.localization.loop_detector``) over the drive so far, and each accepted loop closure is published on
``/seqvpr/loop``: a DiagnosticArray whose one status, ``seqvpr loop``, holds the frame's and its match's stamps,
rows and sessions, the distance and the score (standard messages only: no package to build on the robot). Its grown
past is saved beside the localiser's state (``STATE.loops.npz``).
"""

from __future__ import annotations

import io
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from seqvpr.errors import SeqvprError
from seqvpr.localization.localizer import Localizer
from seqvpr.ros2.dds import DEFAULT, EVERY_SAMPLE, LATCHED, SENSOR_DATA, Bus
from seqvpr.ros2.camera import (
    LEVELS, WARN, TimeGaps, Track, camera_image, fix_in_map, pose_of, stamp_seconds, stamp_text, status_of,
)
from seqvpr.ros2.messages import COMPRESSED, EMPTY, PATH, POSE, STATUS, Received, encode, message, outgoing

POSE_TOPIC, STATUS_TOPIC, RESET_TOPIC, LOOP_TOPIC = "/seqvpr/pose", "/seqvpr/status", "/seqvpr/reset", "/seqvpr/loop"
MATCH_TOPIC, ROUTE_TOPIC = "/seqvpr/match/compressed", "/seqvpr/route"
#: the stamp of what has none (a frame whose bytes do not decode)
ZERO_STAMP = message("builtin_interfaces/msg/Time", sec=0, nanosec=0)


@dataclass(frozen=True)
class NodeSettings:
    """What the node listens to and how: the camera topic and its message type, an optional NavSatFix or Odometry
    topic (its distance to the estimate goes in the status), every frame or the newest (``keep_all``), the frame id
    of what it publishes, where its state is saved on shutdown (None: not saved), and how loop closures are found
    (None: not looked for)."""

    camera: str
    camera_type: str
    fix_topic: str | None = None
    fix_type: str | None = None
    keep_all: bool = False
    frame_id: str = "map"
    state: Path | None = None
    loops: Any = None  # LoopSettings
    publish_images: bool = False


class Inbox:
    """Camera frames from the receiving thread to the localiser: every one in order (``keep_all``), or only the
    newest, counting each one a newer frame replaced before it was processed; and a pending reset."""

    def __init__(self, keep_all: bool) -> None:
        self.keep_all = keep_all
        self.frames: deque = deque()
        self.ready = threading.Condition()
        self.received = self.dropped = 0
        self.reset_pending = False

    def put(self, item: Any) -> None:
        with self.ready:
            self.received += 1
            if not self.keep_all and self.frames:
                self.dropped += len(self.frames)
                self.frames.clear()
            self.frames.append(item)
            self.ready.notify()

    def request_reset(self) -> None:
        with self.ready:
            self.reset_pending = True
            self.ready.notify()

    def get(self, timeout: float) -> tuple[bool, Any]:
        """(whether a reset came first, the next frame or None) within ``timeout`` seconds."""
        with self.ready:
            if not self.frames and not self.reset_pending:
                self.ready.wait(timeout)
            reset, self.reset_pending = self.reset_pending, False
            return reset, (self.frames.popleft() if self.frames else None)


class LocalizerNode:
    """The localiser on DDS: ``run(stop)`` until ``stop`` is set, then the state saved (when asked)."""

    def __init__(self, localizer: Localizer, bus: Bus, settings: NodeSettings) -> None:
        if localizer.encoder is None:  # at start: no camera frame could ever be described
            raise SeqvprError(f"{localizer.saved.folder} holds descriptor-file frames, so camera frames cannot be "
                              "described as its frames: build the map from images (seqvpr map build IMAGES)")
        self.localizer, self.bus, self.settings = localizer, bus, settings
        frames = localizer.saved.frames
        self.track = Track.of(frames.positions, frames.segment_ids, frames.crs)
        self.gaps = TimeGaps()
        self.inbox = Inbox(settings.keep_all)
        self.malformed, self.processed, self.last_error = 0, 0, ""
        self.fix: Any = None
        self.warm_up()
        outputs = EVERY_SAMPLE if settings.keep_all else DEFAULT
        self.pose_writer = bus.writer(POSE_TOPIC, POSE, outputs)
        self.status_writer = bus.writer(STATUS_TOPIC, STATUS, outputs)
        self.route_writer = bus.writer(ROUTE_TOPIC, PATH, LATCHED) if self.track is not None else None
        self.match_writer = bus.writer(MATCH_TOPIC, COMPRESSED, outputs) if settings.publish_images else None
        self.loops, self.loops_found = None, 0
        if settings.loops is not None:
            from seqvpr.localization.loop_detector import LoopDetector

            self.loops = LoopDetector(settings.loops)
            self.loop_writer = bus.writer(LOOP_TOPIC, STATUS, outputs)

    def warm_up(self) -> None:
        """Pay the one-off costs before the first frame, not on it: the message codecs (built on first use), the
        describing network's first pass (and CUDA's start-up). The localiser itself is left untouched."""
        from PIL import Image

        from seqvpr.ros2.messages import COMPRESSED, IMAGE, decode

        head = message("std_msgs/msg/Header", stamp=ZERO_STAMP, frame_id="")
        jpeg = io.BytesIO()
        Image.new("RGB", (64, 48)).save(jpeg, format="JPEG")
        blank = message(IMAGE, header=head, height=1, width=1, encoding="mono8", is_bigendian=0, step=1,
                        data=np.zeros(1, np.uint8)) if self.settings.camera_type == IMAGE else \
            message(COMPRESSED, header=head, format="jpeg", data=np.frombuffer(jpeg.getvalue(), np.uint8))
        camera_image(decode(encode(blank, self.settings.camera_type), self.settings.camera_type),
                     self.settings.camera_type)
        encode(status_of({"state": ""}, 0, "", ZERO_STAMP, "", ""), STATUS)
        if self.track is not None:
            localized = SimpleNamespace(status="localised", index=0, best=0)
            encode(pose_of(localized, 0, self.track, ZERO_STAMP, ""), POSE)
        if self.localizer.encoder is not None:
            self.localizer.encoder.encode(Image.new("RGB", (64, 48)))

    def restore(self, path: Path) -> None:
        """Go on from a saved state (the localiser's, and the time-gap rule's last stamp and steps)."""
        extra = self.localizer.restore(path)
        self.gaps.load(extra.get("time_gaps", {}))
        if self.loops is not None and loop_state_path(path).is_file():
            self.loops.restore(loop_state_path(path))

    def save(self) -> None:
        if self.settings.state is not None:
            self.localizer.save_state(self.settings.state, {"time_gaps": self.gaps.state()})
            if self.loops is not None:
                self.loops.save_state(loop_state_path(self.settings.state))

    def restart(self) -> None:
        """A new segment: the localiser's window and the loop detector's start again."""
        self.localizer.reset()
        if self.loops is not None:
            self.loops.new_segment()

    def run(self, stop: threading.Event) -> None:
        """Process frames until ``stop`` is set; then save the state (when asked)."""
        readers = self._subscribe()  # only now: a frame that came before anyone took it would wait, then be dropped
        if self.route_writer is not None:  # once, latched: RViz or Foxglove joining later still draw it
            from seqvpr.ros2.camera import route_of

            self.route_writer.write(outgoing(PATH, route_of(self.track, self.settings.frame_id)))
        receiver = threading.Thread(target=self._receive, args=(stop, *readers), name="seqvpr-receive", daemon=True)
        receiver.start()
        try:
            while not stop.is_set():
                reset, item = self.inbox.get(0.1)
                if reset:
                    self.restart()
                if item is not None:
                    self.handle(*item)
        finally:
            stop.set()
            receiver.join(timeout=2.0)
            self.save()

    def _subscribe(self) -> tuple:
        """The camera reader (every sample with ``keep_all``, else ROS 2's sensor-data profile), the reset reader and
        the position reader (None without a position topic)."""
        camera = self.bus.reader(self.settings.camera, self.settings.camera_type,
                                 EVERY_SAMPLE if self.settings.keep_all else SENSOR_DATA)
        fixes = self.bus.reader(self.settings.fix_topic, self.settings.fix_type, SENSOR_DATA) \
            if self.settings.fix_topic else None
        return camera, self.bus.reader(RESET_TOPIC, EMPTY, DEFAULT), fixes

    def _receive(self, stop: threading.Event, camera, resets, fixes) -> None:
        """Take every sample as it arrives: frames into the inbox (stamped with their arrival), resets, fixes."""
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.util import duration

        waitset = WaitSet(self.bus.participant)
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        conditions = [ReadCondition(r, mask) for r in (camera, resets, fixes) if r is not None]
        for condition in conditions:
            waitset.attach(condition)
        while not stop.is_set():
            waitset.wait(duration(milliseconds=100))
            for sample in _valid(camera.take(64)):
                self.inbox.put((sample, time.perf_counter()))
            if _valid(resets.take(64)):
                self.inbox.request_reset()
            taken = _valid(fixes.take(64)) if fixes is not None else []
            if taken:
                self.fix = taken[-1].message

    def handle(self, sample: Any, arrived: float) -> dict[str, Any]:
        """One camera sample: decoded, localised (a restart first where the stamps break), published; a malformed
        frame is counted and reported, and leaves the localiser as it was."""
        value = sample.message
        if value is None:
            return self._report_malformed(None, sample.error)
        try:
            image = camera_image(value, self.settings.camera_type)
        except SeqvprError as error:
            return self._report_malformed(value, str(error))
        stamp = stamp_seconds(value)
        if self.gaps.starts_segment(stamp):
            self.restart()
        estimate = self.localizer.update(image, stamp)
        self.processed += 1
        loop = self._find_loop(estimate, stamp, value.header.stamp)
        pose = pose_of(estimate, self.localizer.misses, self.track, value.header.stamp, self.settings.frame_id) \
            if self.track is not None else None
        if pose is not None:
            self.pose_writer.write(outgoing(POSE, pose))
        values = self._values(estimate, value, arrived)
        values["match_image"] = self._publish_match(estimate, value.header.stamp)
        if loop is not None:
            values.update({"loop_match": loop.match if loop.match >= 0 else "", "loop_score": loop.score,
                           "loop_accepted": int(loop.accepted)})
        text = estimate.status if not self.last_error else f"{estimate.status}; last malformed frame: {self.last_error}"
        self.status_writer.write(outgoing(STATUS, status_of(values, LEVELS[estimate.status], text, value.header.stamp,
                                                            self.settings.frame_id, self._hardware_id())))
        return values

    def _publish_match(self, estimate: Any, stamp: Any) -> str | None:
        """With ``publish_images``, the matched map frame's thumbnail on ``/seqvpr/match/compressed`` while localised
        or uncertain: the one the map keeps (``map build --thumbnails``), else one made from the map's source image
        (``seqvpr.data.thumbnails``, once per image, cached); where it came from, for the status (None: none)."""
        if self.match_writer is None or estimate.status not in ("localised", "uncertain") or estimate.best is None:
            return None
        from seqvpr.ros2.camera import header

        row = estimate.index if estimate.status == "localised" else estimate.best
        found = self._thumbnail(row)
        if found is None:
            return None
        data, where = found
        self.match_writer.write(outgoing(COMPRESSED, message(COMPRESSED, header=header(stamp, self.settings.frame_id),
                                                                  format="jpeg", data=np.frombuffer(data, np.uint8))))
        return where

    def _thumbnail(self, row: int) -> tuple[bytes, str] | None:
        """Map frame ``row``'s thumbnail bytes and where they came from (None: neither the map nor its source has
        one)."""
        from seqvpr.data.thumbnails import cached_thumbnail, thumbnail_cache
        from seqvpr.maps.thumbnails import THUMBNAILS_FILE, map_thumbnail

        kept = map_thumbnail(self.localizer.saved.folder, row)
        if kept is not None:
            return kept, f"{THUMBNAILS_FILE}[{row}]"
        images = self.localizer.saved.frames.image_paths
        thumb = cached_thumbnail(images[row], thumbnail_cache()) if images is not None else None
        return (thumb.read_bytes(), str(thumb)) if thumb is not None else None

    def _find_loop(self, estimate: Any, stamp: float | None, header_stamp: Any):
        """The frame's loop closure (None without loop detection, or for a frame the keyframe gate skipped): the
        localiser's own described row goes to the detector; an accepted loop is published on ``/seqvpr/loop``."""
        if self.loops is None or not estimate.kept:
            return None
        loop = self.loops.update(self.localizer.last_kept.numbers, stamp)
        if loop.accepted:
            self.loops_found += 1
            values = {"frame": loop.frame, "stamp": loop.stamp, "match": loop.match, "match_stamp": loop.match_stamp,
                      "session": loop.session, "match_session": loop.match_session, "distance": loop.distance,
                      "score": loop.score, "threshold": self.loops.settings.accept}
            self.loop_writer.write(outgoing(STATUS, status_of(values, 0, "loop closure", header_stamp,
                                                              self.settings.frame_id, self._hardware_id(),
                                                              "seqvpr loop")))
        return loop

    def _report_malformed(self, value: Any, error: str) -> dict[str, Any]:
        self.malformed += 1
        self.last_error = error
        last = self.localizer.last
        values = {"frame": "", "stamp": "" if value is None else stamp_text(value),
                  "state": last.status if last else "warming up", "malformed": self.malformed,
                  "received": self.inbox.received, "dropped": self.inbox.dropped, "error": error}
        stamp = ZERO_STAMP if value is None else value.header.stamp
        self.status_writer.write(outgoing(STATUS, status_of(values, WARN, f"malformed frame: {error}", stamp,
                                                            self.settings.frame_id, self._hardware_id())))
        return values

    def _values(self, estimate: Any, value: Any, arrived: float) -> dict[str, Any]:
        """The status's key-values: the estimate, the stage latencies, what was received, dropped and malformed."""
        names = self.localizer.saved.frames.names
        name = lambda row: "" if row is None or names is None else names[row]  # noqa: E731
        values: dict[str, Any] = {
            "frame": estimate.frame, "stamp": stamp_text(value), "state": estimate.status,
            "map_index": "" if estimate.index is None else estimate.index, "map_frame": name(estimate.index),
            "best_index": "" if estimate.best is None else estimate.best, "best_frame": name(estimate.best),
            "best_session": "" if estimate.best is None else self.localizer.saved.sessions_of_rows(
                np.array([estimate.best]))[0],
            "score": estimate.score, "threshold": self.localizer.threshold,
            **{f"{stage}_ms": float(ms) for stage, ms in estimate.latency.items()},
            "latency_ms": (time.perf_counter() - arrived) * 1e3,
            "received": self.inbox.received, "dropped": self.inbox.dropped, "malformed": self.malformed,
        }
        values["fix_distance_m"] = self._fix_distance(estimate)
        return values

    def _fix_distance(self, estimate: Any) -> float | None:
        """Metres from the latest position fix to the localised map frame (None without both)."""
        if self.fix is None or estimate.index is None or self.track is None:
            return None
        where = fix_in_map(self.fix, self.settings.fix_type, self.track.crs)
        if where is None:
            return None
        x, y = self.track.positions[estimate.index]
        return math.hypot(where[0] - x, where[1] - y)

    def _hardware_id(self) -> str:
        return str(self.localizer.saved.folder)


def loop_state_path(state: Path) -> Path:
    """Where the loop detector's state goes beside the localiser's: ``node.npz`` -> ``node.loops.npz``."""
    state = Path(state)
    return state.with_name(state.name.removesuffix(".npz") + ".loops.npz")


def _valid(samples: list) -> list[Received]:
    """The samples that carry data (a writer leaving sends others: instance state changes)."""
    return [s for s in samples if isinstance(s, Received)]
