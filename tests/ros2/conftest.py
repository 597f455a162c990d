"""DDS for the ROS 2 tests: real cyclonedds participants on the loopback interface, one domain per test (xdist
workers never hear each other), and ``seqvpr`` commands as the processes a user starts."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
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
            "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")]))}


def start_seqvpr(env: dict[str, str], *args) -> subprocess.Popen:
    """``seqvpr ARGS`` as its own process (stdout and stderr kept)."""
    return subprocess.Popen([sys.executable, "-m", "seqvpr.cli", *map(str, args)], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
