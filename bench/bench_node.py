"""Does ``seqvpr node`` keep up with a live camera? A Gardens Point night drive played over DDS (loopback) at
``--rate`` x a ``--fps`` camera into the node with its default drop policy, per descriptor and encoder engine.

Run from the repository root (about a minute on 2 cores, ``../shared/data`` beside the checkout):

    .venv/bin/python bench/bench_node.py --out runs/node-bench
    .venv/bin/python bench/bench_node.py --out runs/node-bench-gpu --device cuda

Per descriptor and drop policy (the default keeps the newest frame; ``--no-drop`` every frame): the day drive
(``day_left``, 200 JPEG frames, NavSatFix a metre a frame) is built into a map, the night drive (``night_right``)
is written as a bag stamped ``1/fps`` s apart and played at ``rate`` x, and every status the node publishes is
recorded. The yardstick is the frame period at that pace (``1000 / (fps x rate)`` ms): the node keeps up when its
p95 latency (frame arrival to publication) stays under it. Reported: frames
received, processed, dropped (the drop policy keeps the newest), latency and localiser time p50/p95, and the
describe cost per descriptor (p50). The table goes to stdout and ``OUT/results.md``.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import cpu_model

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from seqvpr.ros2.messages import COMPRESSED, NAVSATFIX, STATUS, encode, message  # noqa: E402

LOOPBACK = ('<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
            '</General></Domain></CycloneDDS>')
METRES_PER_DEGREE, LAT0, LON0 = 111_320.0, -27.4775, 153.0280


def write_drive(path: Path, images: list[Path], fps: float, offset_m: float) -> None:
    """A ROS 2 bag of JPEG frames ``1/fps`` s apart, each with a NavSatFix (a metre a frame north, ``offset_m``
    east)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from seqvpr.ros2.messages import typestore

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        camera = writer.add_connection("/camera/image_raw/compressed", COMPRESSED, typestore=typestore())
        gps = writer.add_connection("/fix", NAVSATFIX, typestore=typestore())
        for i, file in enumerate(images):
            t = 100.0 + i / fps
            head = message("std_msgs/msg/Header", stamp=message("builtin_interfaces/msg/Time", sec=int(t),
                                                                nanosec=int(round(t % 1 * 1e9)) % 1_000_000_000),
                           frame_id="camera")
            frame = message(COMPRESSED, header=head, format="jpeg", data=np.frombuffer(file.read_bytes(), np.uint8))
            writer.write(camera, int(t * 1e9), encode(frame, COMPRESSED))
            fix = message(NAVSATFIX, header=head, status=message("sensor_msgs/msg/NavSatStatus", status=0, service=1),
                          latitude=LAT0 + i / METRES_PER_DEGREE,
                          longitude=LON0 + offset_m / (METRES_PER_DEGREE * np.cos(np.radians(LAT0))),
                          altitude=30.0, position_covariance=np.zeros(9), position_covariance_type=0)
            writer.write(gps, int(t * 1e9), encode(fix, NAVSATFIX))


def seqvpr(env: dict, *args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "seqvpr.cli", *map(str, args)], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def build_map(name: str, args, env: dict, work: Path) -> Path:
    """The day drive as a map described by ``name``."""
    out = work / f"map-{name}"
    if not out.exists():
        built = subprocess.run([sys.executable, "-m", "seqvpr.cli", "map", "build", work / "day", "--descriptor", name,
                                "--device", args.device, "--out", out], env=env, cwd=ROOT, capture_output=True,
                               text=True)
        if built.returncode:
            raise SystemExit(built.stderr)
    return out


def run_node(name: str, engine: str, policy: str, args, env: dict, work: Path) -> dict:
    """The node over ``name``'s map with drop ``policy`` (default or no-drop) while the night drive plays; its
    statuses and its closing line, as one row."""
    from seqvpr.ros2.dds import Recorder
    from seqvpr.ros2.camera import status_values

    recorder = Recorder("/seqvpr/status", STATUS)
    node = seqvpr(env, "node", "--map", build_map(name, args, env, work), "--topic", "/camera/image_raw/compressed",
                  "--device", args.device, "--engine", engine, "--threshold", "0.01",
                  *(["--no-drop"] if policy == "no-drop" else []))
    played = subprocess.run([sys.executable, "-m", "seqvpr.cli", "play", work / "night", "--rate", str(args.rate),
                             "--wait", "60"], env=env, cwd=ROOT, capture_output=True, text=True)
    processed = int(played.stdout.split()[1]) if played.returncode == 0 else 0
    recorder.wait_for(processed if policy == "no-drop" else 0, 600)  # a node behind works through its backlog
    time.sleep(2.0)
    node.send_signal(signal.SIGTERM)
    _, err = node.communicate(timeout=60)
    recorder.close()
    if played.returncode or node.returncode:
        raise SystemExit(played.stderr + err)
    closing = re.search(r"stopped after (\d+) frames \((\d+) received, (\d+) dropped", err)
    values = [status_values(s.message) for s in recorder.samples]
    column = lambda key: np.array([float(v[key]) for v in values if v.get(key)])  # noqa: E731
    latency, total, describe = column("latency_ms"), column("total_ms"), column("describe_ms")
    processed, received, dropped = (int(g) for g in closing.groups())
    return {"descriptor": name, "engine": engine, "policy": policy, "received": received, "processed": processed, "dropped": dropped,
            "latency": np.percentile(latency, [50, 95]), "total": np.percentile(total, [50, 95]),
            "describe": float(np.percentile(describe, 50))}


def table(rows: list[dict], period: float) -> str:
    lines = ["| descriptor | engine | policy | received | processed | dropped | latency p50 / p95 ms | "
             "localiser p50 / p95 ms | describe p50 ms | p95 latency / frame period |",
             "|---|---|---|---:|---:|---:|---|---|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['descriptor']} | {r['engine']} | {r['policy']} | {r['received']} | {r['processed']} | {r['dropped']} | "
                     f"{r['latency'][0]:.1f} / {r['latency'][1]:.1f} | {r['total'][0]:.1f} / {r['total'][1]:.1f} | "
                     f"{r['describe']:.1f} | {r['latency'][1] / period:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/node-bench"))
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--fps", type=float, default=15.0, help="the camera rate the night drive is stamped at")
    parser.add_argument("--rate", type=float, default=2.0, help="times the recorded pace it is played at")
    parser.add_argument("--descriptors", default="patchnorm,efficientnet-lite0")
    parser.add_argument("--policies", default="default,no-drop", help="drop policies: default (newest frame), no-drop")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--engines", default="torch,auto", help="how the node's encoder runs (--engine)")
    parser.add_argument("--threads", default="2", help="SEQVPR_THREADS of the node (the machine's cores)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    walking = args.data / "gardenspoint_walking"
    for side, bag, offset in (("day_left", "day", 0.0), ("night_right", "night", 0.5)):
        if not (args.out / bag).exists():
            write_drive(args.out / bag, sorted((walking / side).glob("*.jpg")), args.fps, offset)
    env = {**os.environ, "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "77"), "SEQVPR_THREADS": args.threads,
           "CYCLONEDDS_URI": os.environ.get("CYCLONEDDS_URI", LOOPBACK),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")]))}
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "CYCLONEDDS_URI")})
    rows = [run_node(name, engine, policy, args, env, args.out) for name in args.descriptors.split(",")
            for engine in (args.engines.split(",") if name != "patchnorm" else ["torch"])
            for policy in args.policies.split(",")]
    period = 1000.0 / (args.fps * args.rate)
    where = "cuda" if args.device.startswith("cuda") else f"{cpu_model()}, SEQVPR_THREADS={args.threads}"
    report = (f"node at {args.rate:g}x a {args.fps:g} fps camera (frame period {period:.1f} ms), {args.device} "
              f"({where})\n\n{table(rows, period)}\n")
    print(report)
    (args.out / "results.md").write_text(report)


if __name__ == "__main__":
    main()
