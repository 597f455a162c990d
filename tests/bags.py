"""ROS bags for tests, written with ``rosbags`` as a robot records them: camera frames (raw or JPEG) with NavSatFix
fixes, optionally an Odometry topic and a second camera."""

from __future__ import annotations

import numpy as np
from PIL import Image

FRAMES, STEP_S = 30, 0.5
LAT0, LON0, METRES_PER_DEGREE = -27.4775, 153.0280, 111_320.0


def fixes(n: int, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Latitude/longitude of a walk north, one metre a frame (the query side half a metre beside it)."""
    lat = LAT0 + np.arange(n) / METRES_PER_DEGREE
    lon = np.full(n, LON0 + offset / (METRES_PER_DEGREE * np.cos(np.radians(LAT0))))
    return lat, lon


def write_bag(path, images, lat, lon, ros1: bool, storage: str = "mcap", compressed: bool = False,
              odometry: bool = False, statuses=None, zero_stamps: bool = False):
    """Camera frames (raw rgb8 or the JPEG bytes) and NavSatFix fixes 0.1 s apart, as a robot records them (the
    first ``len(lat)`` frames have one; ``statuses``: each fix's NavSatStatus, 0 by default, -1 for no fix); with
    ``odometry``, also a second camera topic and an Odometry topic (x = 2 m a frame, y = -i); ``zero_stamps``: every
    header stamped 0, as a driver without a clock stamps them."""
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
        t = 0.0 if zero_stamps else t
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
            if i >= len(lat):
                continue
            status = 0 if statuses is None else int(statuses[i])
            fix = Fix(header=header(t + 0.1), status=Status(status=status, service=1), latitude=float(lat[i]),
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
