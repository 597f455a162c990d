"""Robot recordings: bags written here with ``rosbags`` itself (ROS 2 mcap and sqlite3, ROS 1), 30 frames of Gardens
Point Walking plus NavSatFix fixes, give the same Recall@K as the image folders they were made from."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.sources import load_traversal
from tests.helpers import raises_one_line, run_cli

FRAMES, STEP_S = 30, 0.5
LAT0, LON0, METRES_PER_DEGREE = -27.4775, 153.0280, 111_320.0


def fixes(n: int, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Latitude/longitude of a walk north, one metre a frame (the query side half a metre beside it)."""
    lat = LAT0 + np.arange(n) / METRES_PER_DEGREE
    lon = np.full(n, LON0 + offset / (METRES_PER_DEGREE * np.cos(np.radians(LAT0))))
    return lat, lon


def image_folder(src, dst, lat, lon):
    """The first FRAMES images of a Gardens Point side, with a positions.csv of the same fixes."""
    dst.mkdir()
    rows = ["image,lat,lon,timestamp"]
    for i, path in enumerate(sorted(src.glob("*.jpg"))[:FRAMES]):
        shutil.copy(path, dst / path.name)
        rows.append(f"{path.name},{lat[i]:.9f},{lon[i]:.9f},{i * STEP_S}")
    (dst / "positions.csv").write_text("\n".join(rows) + "\n")
    return dst


def write_bag(path, images, lat, lon, ros1: bool, storage: str = "mcap", compressed: bool = False,
              odometry: bool = False):
    """Camera frames (raw rgb8 or the JPEG bytes) and NavSatFix fixes 0.1 s apart, as a robot records them; with
    ``odometry``, also a second camera topic and an Odometry topic (x = 2 m a frame, y = -i)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    Img, Cmp, Fix = (store.types[n] for n in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                                             "sensor_msgs/msg/NavSatFix"))
    Header, Time, Status = (store.types[n] for n in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time",
                                                     "sensor_msgs/msg/NavSatStatus"))
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)

    def header(t):
        stamp = Time(sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        return (Header(seq=0, stamp=stamp, frame_id="cam") if ros1 else Header(stamp=stamp, frame_id="cam"))

    with writer:
        camera_type = Cmp.__msgtype__ if compressed else Img.__msgtype__
        camera = writer.add_connection("/camera/image_raw", camera_type, typestore=store)
        gps = writer.add_connection("/gps/fix", Fix.__msgtype__, typestore=store)
        for i, file in enumerate(images):
            t = 100.0 + i * STEP_S
            if compressed:
                message = Cmp(header=header(t), format="jpeg", data=np.frombuffer(file.read_bytes(), np.uint8))
            else:
                pixels = np.asarray(Image.open(file).convert("RGB"))
                message = Img(header=header(t), height=pixels.shape[0], width=pixels.shape[1], encoding="rgb8",
                              is_bigendian=0, step=pixels.shape[1] * 3, data=pixels.reshape(-1))
            writer.write(camera, int(t * 1e9), store.serialize_ros1(message, camera_type) if ros1
                         else store.serialize_cdr(message, camera_type))
            fix = Fix(header=header(t + 0.1), status=Status(status=0, service=1), latitude=float(lat[i]),
                      longitude=float(lon[i]), altitude=30.0, position_covariance=np.zeros(9),
                      position_covariance_type=0)
            writer.write(gps, int((t + 0.1) * 1e9), store.serialize_ros1(fix, Fix.__msgtype__) if ros1
                         else store.serialize_cdr(fix, Fix.__msgtype__))
        if odometry:
            _write_odometry_and_second_camera(writer, store, header, images, ros1)
    return path


def _write_odometry_and_second_camera(writer, store, header, images, ros1: bool):
    """A /camera2 topic (the frames flipped) and an /odom topic stamped with the frames."""
    T = store.types
    Img, Odom = T["sensor_msgs/msg/Image"], T["nav_msgs/msg/Odometry"]
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    camera = writer.add_connection("/camera2/image_raw", Img.__msgtype__, typestore=store)
    odom = writer.add_connection("/odom", Odom.__msgtype__, typestore=store)
    for i, file in enumerate(images):
        t = 100.0 + i * STEP_S
        pixels = np.ascontiguousarray(np.asarray(Image.open(file).convert("RGB"))[:, ::-1])
        frame = Img(header=header(t), height=pixels.shape[0], width=pixels.shape[1], encoding="rgb8",
                    is_bigendian=0, step=pixels.shape[1] * 3, data=pixels.reshape(-1))
        writer.write(camera, int(t * 1e9), serialize(frame, Img.__msgtype__))
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=2.0 * i, y=-float(i), z=0.0),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        message = Odom(header=header(t), child_frame_id="base",
                       pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                       twist=T["geometry_msgs/msg/TwistWithCovariance"](
                           twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)))
        writer.write(odom, int(t * 1e9), serialize(message, Odom.__msgtype__))


@pytest.fixture(scope="module")
def walking(shared_data, tmp_path_factory):
    root = tmp_path_factory.mktemp("walk")
    sides = {}
    for side, offset in (("day_left", 0.0), ("night_right", 0.5)):
        lat, lon = fixes(FRAMES, offset)
        folder = image_folder(shared_data / "gardenspoint_walking" / side, root / side, lat, lon)
        sides[side] = (folder, sorted(folder.glob("*.jpg")), lat, lon)
    return root, sides


def recall(monkeypatch, capsys, out, reference, query):
    code, stdout, err = run_cli(monkeypatch, capsys, "match", "-r", reference, "-q", query, "--radius", "2.5m",
                                "-L", "3", "--descriptor", "efficientnet-lite0", "--image-size", "160x120", "--json",
                                "--out", out)
    assert code == 0, err
    return json.loads(stdout)["recall"]


@pytest.mark.parametrize("kind", ["ros2-mcap", "ros1", "ros2-sqlite3-compressed"])
def test_a_bag_gives_the_recall_of_its_image_folder(walking, tmp_path, monkeypatch, capsys, kind, monkeypatch_env=None):
    root, sides = walking
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    bags = {}
    for side, (_, images, lat, lon) in sides.items():
        name = tmp_path / (f"{side}.bag" if kind == "ros1" else side)
        bags[side] = write_bag(name, images, lat, lon, ros1=kind == "ros1",
                               storage="sqlite3" if "sqlite3" in kind else "mcap", compressed="compressed" in kind)
    from_folders = recall(monkeypatch, capsys, tmp_path / "a", sides["day_left"][0], sides["night_right"][0])
    from_bags = recall(monkeypatch, capsys, tmp_path / "b", f"{bags['day_left']}:/camera/image_raw",
                       bags["night_right"])
    assert from_bags == from_folders and from_folders["1"] > 0.2, (from_bags, from_folders)
    traversal = load_traversal(bags["night_right"], "query")
    np.testing.assert_allclose(traversal.timestamps, 100.0 + np.arange(FRAMES) * STEP_S)
    assert len(traversal) == FRAMES and traversal.positions is not None


def test_bad_topics_are_one_line(walking, tmp_path, monkeypatch):
    _, sides = walking
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    _, images, lat, lon = sides["day_left"]
    bag = write_bag(tmp_path / "b", images[:3], lat, lon, ros1=False)
    raises_one_line("no image topic /nope (its image topics: /camera/image_raw)", load_traversal, f"{bag}:/nope",
                    "reference")


@pytest.mark.parametrize("ros1", [False, True])
def test_topic_options_choose_the_camera_and_the_position_source(walking, tmp_path, monkeypatch, capsys, ros1):
    _, sides = walking
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    _, images, lat, lon = sides["day_left"]
    bag = write_bag(tmp_path / ("r.bag" if ros1 else "r"), images[:6], lat, lon, ros1=ros1, odometry=True)

    def extracted(name, *options):
        code, _, err = run_cli(monkeypatch, capsys, "extract", bag, "--out", tmp_path / name, *options)
        assert code == 0, err
        return np.load(tmp_path / name)

    by_odom = extracted("odom.npz", "--topic", "/camera2/image_raw", "--odom-topic", "/odom")
    np.testing.assert_allclose(by_odom["positions"], np.c_[2.0 * np.arange(6), -np.arange(6.0)])
    by_gps = extracted("gps.npz", "--topic", "/camera/image_raw", "--gps-topic", "/gps/fix")
    steps = np.linalg.norm(np.diff(by_gps["positions"], axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0, atol=0.01)  # one metre a frame north, in UTM
    frames = sorted((tmp_path / "frames").rglob("*.png"))
    assert len(frames) == 12  # six frames of each camera, decoded once each
    first = load_traversal(f"{bag}:/camera2/image_raw", "query").image_paths[0]
    np.testing.assert_array_equal(np.asarray(Image.open(first)),
                                  np.asarray(Image.open(images[0]).convert("RGB"))[:, ::-1])


def test_bad_topic_options_are_one_line(walking, tmp_path, monkeypatch, capsys):
    _, sides = walking
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    _, images, lat, lon = sides["day_left"]
    bag = write_bag(tmp_path / "r", images[:3], lat, lon, ros1=False, odometry=True)
    out = tmp_path / "o.npz"
    for options, fragment in [
        ((), "name the image topic with --topic (its image topics: /camera/image_raw, /camera2/image_raw)"),
        (("--topic", "/camera/image_raw", "--gps-topic", "/odom"), "no NavSatFix topic /odom (its NavSatFix topics: /gps/fix)"),
        (("--topic", "/camera/image_raw", "--odom-topic", "/gps/fix"), "no Odometry topic /gps/fix"),
        (("--topic", "/camera/image_raw", "--gps-topic", "/gps/fix", "--odom-topic", "/odom"), "not both"),
        (("--topic", "/camera/image_raw", "--stamp-tolerance", "0"), "'--stamp-tolerance': 0 is not in (0, inf]"),
    ]:
        code, _, err = run_cli(monkeypatch, capsys, "extract", bag, "--out", out, *options)
        assert (code, err.count("\n")) == (2, 1) and fragment in err, (options, err)
        assert not out.exists()
    code, _, err = run_cli(monkeypatch, capsys, "extract", images[0].parent, "--out", out, "--topic", "/camera/image_raw")
    assert code == 2 and "--topic: for ROS bag sources, and no source here is a bag" in err, err


def test_a_bag_source_text_reads_back_what_it_names(tmp_path):
    from seqvpr.data.loaders.rosbag import BagTopics, bag_source, parse_bag_source

    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    for topics in [BagTopics(), BagTopics("/cam/image"), BagTopics(None, "/fix"), BagTopics("/c", None, "/odom", 0.2)]:
        assert parse_bag_source(bag_source(bag, topics)) == (bag, topics)
    assert parse_bag_source(str(tmp_path / "run.npz")) is None
    raises_one_line("'speed' is not a bag option", parse_bag_source, f"{bag}?speed=2")
