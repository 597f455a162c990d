"""What the node publishes, recorded into a ROS 2 bag (``seqvpr play --record OUT``): its status, pose, loop and
matched-image topics, each sample as the bytes that came, stamped with its header's stamp (the camera frame's).
``seqvpr view OUT`` opens the bag as a localisation run. The bag folder is written under a temporary name and
renamed (``io.atomic_folder``)."""

from __future__ import annotations

import time
from pathlib import Path

from seqvpr.io import atomic_folder
from seqvpr.ros2.dds import EVERY_SAMPLE, Recorder
from seqvpr.ros2.messages import COMPRESSED, POSE, STATUS, typestore

#: the node's topics a recording keeps, and their types
NODE_TOPICS = (("/seqvpr/status", STATUS), ("/seqvpr/pose", POSE), ("/seqvpr/loop", STATUS),
               ("/seqvpr/match/compressed", COMPRESSED))
BAG_MARKER = "metadata.yaml"


class NodeRecording:
    """Subscribers to every node topic, started before the play so nothing published is missed."""

    def __init__(self, domain: int | None = None) -> None:
        self.recorders = {topic: (msgtype, Recorder(topic, msgtype, domain, EVERY_SAMPLE))
                          for topic, msgtype in NODE_TOPICS}

    def finish(self, out: str | Path, settle: float = 2.0) -> dict[str, int]:
        """Wait ``settle`` seconds for the node's last answers, stop, write the bag; samples a topic."""
        time.sleep(settle)
        for _, recorder in self.recorders.values():
            recorder.close()
        write_node_bag(out, {topic: (msgtype, list(recorder.samples))
                             for topic, (msgtype, recorder) in self.recorders.items()})
        return {topic: len(recorder.samples) for topic, (_, recorder) in self.recorders.items()}


def write_node_bag(out: str | Path, samples: dict[str, tuple[str, list]]) -> Path:
    """A ROS 2 bag (MCAP) at ``out`` of each topic's samples (``Received``), stamped with their header stamps."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    with atomic_folder(out, BAG_MARKER) as tmp:
        tmp.rmdir()  # the writer makes the bag's folder itself
        with Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            for topic, (msgtype, received) in samples.items():
                if not received:
                    continue
                connection = writer.add_connection(topic, msgtype, typestore=store)
                for sample in received:
                    stamp = sample.message.header.stamp if sample.message is not None else None
                    nanoseconds = 0 if stamp is None else int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
                    writer.write(connection, nanoseconds, bytes(sample.data))
    return Path(out)
