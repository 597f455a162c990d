"""The node's plain parts: camera messages to images (as a bag's frames are decoded), malformed frames as one line,
the causal time-gap rule against the recording's, the drop policy, and estimates as poses."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from seqvpr.data.images import raw_pixels, read_image
from seqvpr.data.loaders.dbstruct import time_gap_segments
from seqvpr.ros2.camera import (
    TimeGaps, Track, camera_image, camera_type, fix_in_map, pose_covariance, pose_of, status_of, status_values,
)
from seqvpr.ros2.messages import COMPRESSED, IMAGE, decode, encode, message
from seqvpr.ros2.node import Inbox
from tests.helpers import raises_one_line


def header(sec: int = 7, nanosec: int = 5):
    return message("std_msgs/msg/Header", stamp=message("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec),
                   frame_id="cam")


def raw(pixels: np.ndarray, encoding: str, step: int | None = None, data=None):
    h, w = pixels.shape[:2]
    row = w * (pixels.shape[2] if pixels.ndim == 3 else 1) * pixels.dtype.itemsize
    return message(IMAGE, header=header(), height=h, width=w, encoding=encoding, is_bigendian=0,
                   step=step or row, data=np.ascontiguousarray(pixels).view(np.uint8).ravel() if data is None else data)


RNG = np.random.default_rng(0)
RGB = RNG.integers(0, 256, (6, 5, 3), dtype=np.uint8)


@pytest.mark.parametrize("encoding,pixels,expected", [
    ("rgb8", RGB, RGB),
    ("bgr8", RGB[..., ::-1].copy(), RGB),
    ("rgba8", np.concatenate([RGB, np.full((6, 5, 1), 9, np.uint8)], 2), RGB),
    ("bgra8", np.concatenate([RGB[..., ::-1], np.full((6, 5, 1), 9, np.uint8)], 2), RGB),
    ("mono8", RGB[..., 0].copy(), np.repeat(RGB[..., :1], 3, 2)),
    ("mono16", RGB[..., 0].astype("<u2") * 256 + 77, np.repeat(RGB[..., :1], 3, 2)),
])
def test_raw_frames_decode_to_the_pixels_they_hold(encoding, pixels, expected):
    image = camera_image(decode(encode(raw(pixels, encoding), IMAGE), IMAGE), IMAGE)
    assert np.array_equal(np.asarray(image), expected)


def test_a_compressed_frame_decodes_as_the_same_bytes_read_from_a_file(tmp_path):
    """The node decodes a CompressedImage's bytes as ``seqvpr localize`` decodes the bag's cached file of them."""
    buffer = io.BytesIO()
    Image.fromarray(RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)).save(buffer, format="JPEG", quality=80)
    (tmp_path / "f.jpg").write_bytes(buffer.getvalue())
    value = message(COMPRESSED, header=header(), format="jpeg", data=np.frombuffer(buffer.getvalue(), np.uint8))
    assert np.array_equal(np.asarray(camera_image(value, COMPRESSED)), np.asarray(read_image(tmp_path / "f.jpg")))


@pytest.mark.parametrize("value,match", [
    (raw(RGB, "rgb8", data=np.zeros(10, np.uint8)), "10 bytes of pixels, where a 5x6 rgb8 image with step 15 holds 90"),
    (raw(RGB, "yuv422"), "image encoding 'yuv422' is not supported"),
    (raw(RGB[:0], "rgb8"), "an empty image"),
    (raw(RGB, "rgb8", step=3), "step 3 is shorter than a row"),
    (message(COMPRESSED, header=header(), format="jpeg", data=np.zeros(0, np.uint8)), "an empty compressed image"),
    (message(COMPRESSED, header=header(), format="jpeg", data=np.arange(50, dtype=np.uint8)), "not a readable jpeg"),
])
def test_malformed_frames_are_one_line_naming_the_frame(value, match):
    msgtype = COMPRESSED if hasattr(value, "format") else IMAGE
    text = raises_one_line(match, camera_image, value, msgtype)
    assert text.startswith("frame 7.000000005:")


def test_raw_pixels_are_the_bag_loaders():
    """One decoding for bags and live frames: the loader's cached PNG holds what ``raw_pixels`` gives."""
    assert np.array_equal(raw_pixels("bgr8", 6, 5, 15, False, RGB[..., ::-1].tobytes(), "x"), RGB)


def test_the_camera_type_follows_image_transports_names():
    assert camera_type("/camera/image_raw") == IMAGE
    assert camera_type("/camera/image_raw/compressed") == COMPRESSED
    assert camera_type("/camera/image_raw", "compressed") == COMPRESSED


def causal_segments(stamps) -> np.ndarray:
    gaps = TimeGaps()
    return np.cumsum([gaps.starts_segment(float(s)) for s in stamps])


@settings(max_examples=60, deadline=None)
@given(st.integers(12, 80), st.floats(0.01, 2.0), st.lists(st.tuples(st.integers(0, 10_000), st.floats(11, 1e4)),
                                                             max_size=4), st.integers(0, 2**31))
def test_the_live_gap_rule_is_the_recordings_once_the_rate_is_known(n, step, gaps, seed):
    """On a camera at a steady rate with jitter, and gaps after the first 10 frames, restarting where the causal
    rule says gives the segments of ``time_gap_segments`` over the whole recording."""
    rng = np.random.default_rng(seed)
    steps = step * (1 + rng.uniform(-0.05, 0.05, n - 1))
    for where, factor in gaps:
        steps[10 + where % max(n - 11, 1)] = step * factor
    stamps = np.concatenate([[100.0], 100.0 + np.cumsum(steps)])
    assert np.array_equal(causal_segments(stamps), time_gap_segments(stamps))


def test_a_stamp_going_back_restarts():
    assert causal_segments([1.0, 2.0, 3.0, 2.5, 3.5]).tolist() == [0, 0, 0, 1, 1]


def test_the_gap_rule_saves_and_loads():
    gaps, again = TimeGaps(), TimeGaps()
    for s in (1.0, 2.0, 3.0):
        gaps.starts_segment(s)
    again.load(gaps.state())
    assert again.starts_segment(40.0) and not TimeGaps().starts_segment(40.0)
    raises_one_line("time-gap record is malformed", again.load, {"last": "x", "steps": []})


def test_the_inbox_keeps_every_frame_or_the_newest_counting_the_rest():
    every, newest = Inbox(keep_all=True), Inbox(keep_all=False)
    for i in range(5):
        every.put(i)
        newest.put(i)
    assert [every.get(0)[1] for _ in range(5)] == [0, 1, 2, 3, 4] and every.dropped == 0
    assert newest.get(0) == (False, 4) and newest.dropped == 4 and newest.received == 5
    newest.request_reset()
    assert newest.get(0) == (True, None)


class Seen:
    def __init__(self, status, index=None, best=None):
        self.status, self.index, self.best = status, index, best


def test_poses_are_the_matched_frame_and_grow_uncertain():
    positions = np.column_stack([np.zeros(5), np.arange(5.0) * 2.0])  # north, 2 m a frame
    track = Track.of(positions, np.zeros(5, np.int64), "local")
    assert track.spacing == 2.0 and np.allclose(track.headings, math.pi / 2)
    stamp = header().stamp
    assert pose_of(Seen("warming up"), 0, track, stamp, "map") is None
    assert pose_of(Seen("lost", None, 3), 5, track, stamp, "map") is None
    sure = pose_of(Seen("localised", 3, 3), 0, track, stamp, "map")
    unsure = pose_of(Seen("uncertain", None, 2), 2, track, stamp, "map")
    assert (sure.pose.pose.position.x, sure.pose.pose.position.y) == (0.0, 6.0)
    assert unsure.pose.pose.position.y == 4.0 and sure.header.stamp.nanosec == 5
    assert math.isclose(2 * math.atan2(sure.pose.pose.orientation.z, sure.pose.pose.orientation.w), math.pi / 2)
    assert sure.pose.covariance[0] == 4.0 and unsure.pose.covariance[0] == 36.0
    assert unsure.pose.covariance[35] > sure.pose.covariance[35]
    assert Track.of(None, np.zeros(3), None) is None


def test_a_segment_of_one_frame_has_no_heading():
    track = Track.of(np.array([[0.0, 0.0], [5.0, 5.0], [6.0, 5.0]]), np.array([0, 1, 1]), "local")
    assert math.isnan(track.headings[0]) and track.headings[1] == 0.0
    assert pose_covariance(1.0, 0, False)[35] == 1e6


def test_status_values_read_back_exactly():
    sent = status_of({"score": 0.1 + 0.2, "map_index": 4, "fix_distance_m": None}, 0, "localised", header().stamp,
                     "map", "maps/x")
    values = status_values(decode(encode(sent, "diagnostic_msgs/msg/DiagnosticArray"),
                                  "diagnostic_msgs/msg/DiagnosticArray"))
    assert float(values["score"]) == 0.1 + 0.2 and values["map_index"] == "4" and values["fix_distance_m"] == ""


def test_fixes_meet_the_map_in_its_coordinates():
    from seqvpr.data.geo import latlon_to_utm

    xy, crs = latlon_to_utm(np.array([-27.4775]), np.array([153.028]), "x")
    fix = message("sensor_msgs/msg/NavSatFix", header=header(), status=message(
        "sensor_msgs/msg/NavSatStatus", status=0, service=1), latitude=-27.4775, longitude=153.028, altitude=0.0,
        position_covariance=np.zeros(9), position_covariance_type=0)
    assert np.allclose(fix_in_map(fix, "sensor_msgs/msg/NavSatFix", crs), xy[0])
    assert fix_in_map(fix, "sensor_msgs/msg/NavSatFix", "local") is None
