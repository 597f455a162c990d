"""DDS as ROS 2 uses it, through cyclonedds (the ``ros2`` extra): a participant in ``ROS_DOMAIN_ID``'s domain, and
readers and writers of ROS 2 topics (``rt/`` + the topic, ROS 2's type names) with ROS 2's QoS profiles."""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass

from seqvpr.errors import SeqvprError
from seqvpr.ros2.messages import Received, dds_topic, wire_type

#: the highest domain id ROS 2 allows (ports stay valid on every platform)
MAX_DOMAIN = 232


def require_cyclonedds() -> None:
    """cyclonedds is importable, else one line naming the extra that installs it."""
    try:
        import cyclonedds.domain  # noqa: F401
    except ImportError:
        raise SeqvprError("seqvpr speaks ROS 2 over DDS through cyclonedds: pip install 'seqvpr[ros2]'") from None


def domain_id(given: int | None = None) -> int:
    """The DDS domain: ``given``, else ``$ROS_DOMAIN_ID`` (ROS 2's variable), else 0; one line if it is not 0-232."""
    text = str(given) if given is not None else os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not text.isdigit() or int(text) > MAX_DOMAIN:
        raise SeqvprError(f"ROS_DOMAIN_ID must be a whole number from 0 to {MAX_DOMAIN}, got {text!r}")
    return int(text)


@dataclass(frozen=True)
class Profile:
    """A QoS profile as ROS 2 names its parts: reliable or best effort, keep last ``depth`` (0: keep all), volatile
    or transient-local (``latched``: a late subscriber still gets the last ``depth`` samples)."""

    reliable: bool
    depth: int
    latched: bool = False

    def qos(self):
        from cyclonedds.core import Policy, Qos
        from cyclonedds.util import duration

        reliability = Policy.Reliability.Reliable(duration(seconds=1)) if self.reliable else \
            Policy.Reliability.BestEffort
        history = Policy.History.KeepLast(self.depth) if self.depth else Policy.History.KeepAll
        durability = Policy.Durability.TransientLocal if self.latched else Policy.Durability.Volatile
        return Qos(reliability, history, durability)


#: ROS 2's sensor-data profile (rmw_qos_profile_sensor_data): best effort, keep last 5
SENSOR_DATA = Profile(False, 5)
#: ROS 2's default profile for publishers and subscribers: reliable, keep last 10
DEFAULT = Profile(True, 10)
#: every sample, none lost (a replay's subscriber: ``seqvpr node --no-drop``; ``seqvpr play``'s publishers)
EVERY_SAMPLE = Profile(True, 0)
#: a latched topic (ROS 2's transient-local): the map's route, published once, reaches subscribers that join later
LATCHED = Profile(True, 1, latched=True)


class Bus:
    """One DDS participant: readers and writers of ROS 2 topics by ROS 2 name and message type."""

    def __init__(self, domain: int | None = None) -> None:
        require_cyclonedds()
        from cyclonedds.domain import DomainParticipant

        self.domain = domain_id(domain)
        self.participant = DomainParticipant(self.domain)
        self.topics: dict[str, object] = {}

    def _topic(self, topic: str, msgtype: str):
        from cyclonedds.topic import Topic

        name = dds_topic(topic)
        if name not in self.topics:
            self.topics[name] = Topic(self.participant, name, wire_type(msgtype))
        return self.topics[name]

    def writer(self, topic: str, msgtype: str, profile: Profile = DEFAULT):
        from cyclonedds.pub import DataWriter

        return DataWriter(self.participant, self._topic(topic, msgtype), qos=profile.qos())

    def reader(self, topic: str, msgtype: str, profile: Profile = DEFAULT):
        from cyclonedds.sub import DataReader

        return DataReader(self.participant, self._topic(topic, msgtype), qos=profile.qos())


def wait_for_match(writer, seconds: float) -> bool:
    """Wait up to ``seconds`` until a reader matches ``writer``; whether one did."""
    deadline = time.monotonic() + seconds
    while not writer.get_matched_subscriptions():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


class Recorder:
    """Every sample of a topic as it arrives (a reliable, keep-all subscriber read by a thread of its own): what
    ``ros2 topic echo`` shows, kept for a test or a benchmark to read."""

    def __init__(self, topic: str, msgtype: str, domain: int | None = None, profile: Profile = EVERY_SAMPLE) -> None:
        self.bus = Bus(domain)
        self.reader = self.bus.reader(topic, msgtype, profile)
        self.samples: list[Received] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._take, name=f"seqvpr-record{topic}", daemon=True)
        self._thread.start()

    def _take(self) -> None:
        while not self._stop.is_set():
            self.samples.extend(s for s in self.reader.take(256) if isinstance(s, Received))
            time.sleep(0.005)

    def wait_for(self, count: int, seconds: float) -> list:
        """The samples once ``count`` came (or ``seconds`` passed)."""
        deadline = time.monotonic() + seconds
        while len(self.samples) < count and time.monotonic() < deadline:
            time.sleep(0.02)
        return list(self.samples)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
