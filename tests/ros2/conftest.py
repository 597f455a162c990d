"""DDS for the ROS 2 tests: real cyclonedds participants on the loopback interface, one domain per test (xdist
workers never hear each other), and ``seqvpr`` commands as the processes a user starts."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds", reason="the ros2 extra (cyclonedds) is not installed")

ROOT = Path(__file__).resolve().parents[2]
LOOPBACK = ('<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
            '</General></Domain></CycloneDDS>')
_DOMAINS = itertools.count()


@pytest.fixture
def dds(monkeypatch) -> dict[str, str]:
    """A domain of this test's own on loopback, set for this process and returned as the environment of the
    processes it starts."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    domain = str(1 + (worker * 37 + next(_DOMAINS)) % 230)
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    return {**os.environ, "ROS_DOMAIN_ID": domain, "CYCLONEDDS_URI": LOOPBACK, "SEQVPR_THREADS": "1",
            "PYTHONPATH": str(ROOT / "src")}


def start_seqvpr(env: dict[str, str], *args) -> subprocess.Popen:
    """``seqvpr ARGS`` as its own process (stdout and stderr kept)."""
    return subprocess.Popen([sys.executable, "-m", "seqvpr.cli", *map(str, args)], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


class Collector:
    """Every sample of a topic, taken by a thread of this process (a reliable, keep-all subscriber)."""

    def __init__(self, topic: str, msgtype: str) -> None:
        from seqvpr.ros2.dds import EVERY_SAMPLE, Bus

        self.bus = Bus()
        self.reader = self.bus.reader(topic, msgtype, EVERY_SAMPLE)
        self.samples: list = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._take, daemon=True)
        self.thread.start()

    def _take(self) -> None:
        while not self.stop.is_set():
            self.samples.extend(self.reader.take(256))
            time.sleep(0.005)

    def wait_for(self, count: int, seconds: float) -> list:
        """The samples once ``count`` came (or ``seconds`` passed)."""
        deadline = time.monotonic() + seconds
        while len(self.samples) < count and time.monotonic() < deadline:
            time.sleep(0.02)
        return list(self.samples)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
