"""``seqvpr node`` and ``seqvpr play`` over real DDS on loopback, as a robot engineer runs them: a Gardens Point
night drive played into the node gives, frame for frame, what ``seqvpr localize`` gives on the same bag; a SIGTERM
mid-stream and a restart with ``--restore`` go on as if uninterrupted; malformed frames are counted, not fatal."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.geo import latlon_to_utm
from seqvpr.ros2.camera import status_values
from seqvpr.ros2.messages import EMPTY, IMAGE, POSE, STATUS, message, outgoing
from tests.bags import fixes, write_bag
from tests.helpers import run_cli, write_image_folder
from seqvpr.ros2.dds import Recorder
from tests.ros2.conftest import ROOT, start_seqvpr

pytestmark = pytest.mark.slow
NODE = ("--topic", "/camera/image_raw", "--image-type", "compressed", "--threshold", "0.01")


def seqvpr(*args) -> str:
    """Run a ``seqvpr`` command to its end; its stdout."""
    env = {"SEQVPR_THREADS": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT / "src"), "HOME": str(Path.home())}
    done = subprocess.run([sys.executable, "-m", "seqvpr.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


@pytest.fixture(scope="module")
def drive(shared_data, tmp_path_factory):
    """Gardens Point Walking written as two drives (JPEG frames, NavSatFix a metre a frame, 0.5 s apart): the day
    drive's map, the night bag, and what ``seqvpr localize`` reports for it frame by frame."""
    root = tmp_path_factory.mktemp("drive")
    for side, offset in (("day_left", 0.0), ("night_right", 0.5)):
        images = sorted((shared_data / "gardenspoint_walking" / side).glob("*.jpg"))
        write_bag(root / side, images, *fixes(len(images), offset), ros1=False, compressed=True)
    seqvpr("map", "build", root / "day_left", "--out", root / "map")
    seqvpr("localize", "--map", root / "map", "-q", root / "night_right", "--threshold", "0.01", "--out", root / "loc")
    with open(root / "loc" / "stream.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    return root, rows


def same_as_localize(statuses: list[dict], rows: list[dict]) -> list[str]:
    """Where the node's published estimates differ from ``seqvpr localize``'s rows (index, best, score, state)."""
    wrong = []
    for i, (got, want) in enumerate(zip(statuses, rows, strict=True)):
        score = "" if got["score"] == "nan" else f"{float(got['score']):.6f}"
        if (got["state"], got["map_index"], got["best_index"], score) != \
                (want["status"], want["localised_row"], want["best_row"], want["score"]):
            wrong.append(f"frame {i}: {got} != {want}")
    return wrong


def stop(node: subprocess.Popen) -> tuple[str, str]:
    node.send_signal(signal.SIGTERM)
    out, err = node.communicate(timeout=60)
    assert node.returncode == 0, err
    return out, err


def test_a_bag_played_into_the_node_equals_seqvpr_localize(drive, dds):
    root, rows = drive
    statuses, poses = Recorder("/seqvpr/status", STATUS), Recorder("/seqvpr/pose", POSE)
    node = start_seqvpr(dds, "node", "--map", root / "map", *NODE, "--no-drop", "--gps-topic", "/gps/fix")
    try:
        played = subprocess.run([sys.executable, "-m", "seqvpr.cli", "play", root / "night_right", "--rate", "20",
                                 "--wait", "30"], env=dds, cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert played.returncode == 0 and "played 200 frames of /camera/image_raw and 200 fixes" in played.stdout, \
            played.stderr
        got = [status_values(s.message) for s in statuses.wait_for(len(rows), 120)]
        pose_messages = poses.wait_for(sum(r["status"] in ("localised", "uncertain") for r in rows), 30)
    finally:
        _, err = stop(node)
        statuses.close()
        poses.close()
    assert len(got) == len(rows) == 200
    assert same_as_localize(got, rows) == []
    assert "stopped after 200 frames (200 received, 0 dropped, 0 malformed)" in err
    # the distance from the latest fix (this frame's, or the one before: a metre apart) to the localised frame
    fix_xy, _ = latlon_to_utm(*fixes(len(rows), 0.5), "night")
    for i, (v, r) in enumerate(zip(got, rows)):
        if r["status"] == "localised" and i > 0:
            expected = np.hypot(*(fix_xy[i] - [float(r["x"]), float(r["y"])]))
            assert abs(float(v["fix_distance_m"]) - expected) <= 1.01, (i, v["fix_distance_m"], expected)
    localized = [(int(r["localised_row"]), float(r["x"]), float(r["y"])) for r in rows if r["status"] == "localised"]
    placed = {(p.message.pose.pose.position.x, p.message.pose.pose.position.y) for p in pose_messages}
    assert len(pose_messages) == sum(r["status"] in ("localised", "uncertain") for r in rows)
    assert all((round(x, 3), round(y, 3)) in {(round(a, 3), round(b, 3)) for a, b in placed} for _, x, y in localized)


def test_sigterm_mid_stream_saves_the_state_and_restore_goes_on_as_uninterrupted(drive, dds, tmp_path):
    root, rows = drive
    state = tmp_path / "node.npz"
    statuses = Recorder("/seqvpr/status", STATUS)
    node = start_seqvpr(dds, "node", "--map", root / "map", *NODE, "--no-drop", "--state", state)
    player = start_seqvpr(dds, "play", root / "night_right", "--rate", "8", "--wait", "30")
    try:
        statuses.wait_for(60, 120)
        _, err = stop(node)  # mid-stream: the player is still publishing
        assert player.poll() is None
    finally:
        player.kill()
        player.communicate()
        statuses.close()
    assert f"state saved to {state}" in err
    with np.load(state, allow_pickle=False) as saved:
        done = json.loads(str(saved["header"]))["frame"]
    assert 60 <= done < 200
    statuses = Recorder("/seqvpr/status", STATUS)
    node = start_seqvpr(dds, "node", "--map", root / "map", *NODE, "--no-drop", "--state", state, "--restore")
    try:
        subprocess.run([sys.executable, "-m", "seqvpr.cli", "play", root / "night_right", "--rate", "20", "--wait",
                        "30", "--frames", f"{done}:"], env=dds, cwd=ROOT, check=True, capture_output=True, timeout=300)
        got = [status_values(s.message) for s in statuses.wait_for(200 - done, 120)]
    finally:
        stop(node)
        statuses.close()
    assert [int(v["frame"]) for v in got] == list(range(done, 200))
    assert same_as_localize(got, rows[done:]) == []


@pytest.fixture
def small_map(tmp_path):
    """A map of 12 small synthetic frames (patch-normalised), for the node's fault handling."""
    folder = write_image_folder(tmp_path / "frames", 12, (4, 6), (48, 32))
    seqvpr("map", "build", folder, "--out", tmp_path / "map")
    return tmp_path / "map"


def frame(i: int, encoding: str = "rgb8", size: int | None = None):
    pixels = np.random.default_rng(i).integers(0, 255, (32, 48, 3), dtype=np.uint8)
    data = pixels.ravel() if size is None else np.zeros(size, np.uint8)
    stamp = message("builtin_interfaces/msg/Time", sec=100 + i, nanosec=0)
    return message(IMAGE, header=message("std_msgs/msg/Header", stamp=stamp, frame_id="cam"), height=32, width=48,
                   encoding=encoding, is_bigendian=0, step=144, data=data)


def test_malformed_frames_are_counted_and_reported_never_a_crash(small_map, dds):
    from seqvpr.ros2.dds import EVERY_SAMPLE, Bus, wait_for_match

    statuses = Recorder("/seqvpr/status", STATUS)
    node = start_seqvpr(dds, "node", "--map", small_map, "--no-drop", "-L", "2")
    try:
        writer = Bus().writer("/camera/image_raw", IMAGE, EVERY_SAMPLE)
        assert wait_for_match(writer, 30)
        for value in (frame(0), frame(1, size=10), frame(2, "yuv422"), frame(3, size=0), frame(4), frame(5)):
            writer.write(outgoing(IMAGE, value))
        got = [status_values(s.message) for s in statuses.wait_for(6, 60)]
        reset = Bus().writer("/seqvpr/reset", EMPTY, EVERY_SAMPLE)
        assert wait_for_match(reset, 30)
        reset.write(outgoing(EMPTY, message(EMPTY, structure_needs_at_least_one_member=0)))
        time.sleep(1.0)  # the reset is on its own topic: let it arrive before the next frame
        writer.write(outgoing(IMAGE, frame(6)))
        after = status_values(statuses.wait_for(7, 60)[-1].message)
        levels = [s.message.status[0].message for s in statuses.samples]
    finally:
        _, err = stop(node)
        statuses.close()
    assert [v["malformed"] for v in got] == ["0", "1", "2", "3", "3", "3"]
    assert "10 bytes of pixels" in got[1]["error"] and "'yuv422' is not supported" in got[2]["error"]
    assert "0 bytes of pixels" in got[3]["error"] and levels[1].startswith("malformed frame: ")
    assert [got[i]["frame"] for i in (0, 4, 5)] == ["0", "1", "2"] and "3 malformed" in err
    assert got[0]["state"] == "warming up" and got[4]["state"] != "warming up"
    assert after["state"] == "warming up" and after["frame"] == "3"  # /seqvpr/reset restarted the window


def test_a_map_or_model_mismatch_is_one_line_at_start_up(small_map, tmp_path, monkeypatch, capsys):
    from seqvpr.models.configs import TransformConfig
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet

    save_seqmatchnet(tmp_path / "smn", FrameTransform(TransformConfig(16, out_dim=8), seed=3), {})
    for args, said in [(("--model", tmp_path / "smn"), "build the map through the SeqMatchNet model"),
                       (("-L", "50"), "--seq-len 50 is longer than every segment"),
                       (("--restore",), "--restore starts from the state in --state")]:
        code, out, err = run_cli(monkeypatch, capsys, "node", "--map", small_map, *args)
        assert code == 2 and len(error_lines(err)) == 1 and said in error_lines(err)[0], err
    code, _, err = run_cli(monkeypatch, capsys, "node", "--map", tmp_path / "nowhere")
    assert code == 2 and len(error_lines(err)) == 1 and "nowhere" in err
    from tests.helpers import write_route_files

    (tmp_path / "route").mkdir()
    route = write_route_files(tmp_path / "route", n_frames=40, dim=8, seed=1)
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "descriptors")[0] == 0
    code, out, err = run_cli(monkeypatch, capsys, "node", "--map", tmp_path / "descriptors", "-L", "3")
    assert code == 2 and "holds descriptor-file frames" in error_lines(err)[0] and "listening" not in out + err, err


def error_lines(err: str) -> list[str]:
    """The error lines a command printed (progress lines may come before them)."""
    return [line for line in err.splitlines() if line.startswith("seqvpr: error:")]


def test_without_cyclonedds_the_commands_name_the_extra(small_map, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "cyclonedds", None)
    monkeypatch.setitem(sys.modules, "cyclonedds.domain", None)
    for args in (("node", "--map", small_map), ("play", small_map)):
        code, _, err = run_cli(monkeypatch, capsys, *args)
        assert code == 2 and len(error_lines(err)) == 1 and "pip install 'seqvpr[ros2]'" in err, err


def tiny_images(folder: Path, n: int) -> list[Path]:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(1)
    files = [folder / f"{i:03d}.png" for i in range(n)]
    for file in files:
        Image.fromarray(rng.integers(0, 255, (8, 12, 3), dtype=np.uint8)).save(file)
    return files


@pytest.mark.parametrize("ros1", [False, True])
def test_play_publishes_a_range_of_frames_and_their_fixes_as_ros2_messages(tmp_path, dds, ros1):
    """A ROS 2 bag's frames go out as its bytes, a ROS 1 bag's as the same ROS 2 messages; ``frames`` picks camera
    frames in recorded order and the fixes from a second before them."""
    from seqvpr.data.loaders.rosbag import BagTopics
    from seqvpr.ros2.dds import Bus
    from seqvpr.ros2.messages import NAVSATFIX
    from seqvpr.ros2.play import play_bag

    files = tiny_images(tmp_path / "img", 12)
    bag = write_bag(tmp_path / ("drive.bag" if ros1 else "drive"), files, *fixes(12), ros1=ros1)
    frames, gps = Recorder("/camera/image_raw", IMAGE), Recorder("/gps/fix", NAVSATFIX)
    try:
        played = play_bag(bag, BagTopics(), Bus(), rate=50.0, frames="4:9", wait=30)
        got, fixed = frames.wait_for(5, 30), gps.wait_for(7, 30)
    finally:
        frames.close()
        gps.close()
    # frames 0.5 s apart, each fix 0.1 s after its frame: fixes 2-8 lie from 1 s before frame 4 to frame 9
    assert (played.frames, played.fixes, played.matched) == (5, 7, True)
    pixels = [np.asarray(Image.open(f).convert("RGB")) for f in files[4:9]]
    assert [np.array_equal(s.message.data.reshape(8, 12, 3), p) for s, p in zip(got, pixels)] == [True] * 5
    assert [s.message.header.stamp.sec for s in got] == [102, 102, 103, 103, 104]
    assert len(fixed) == 7 and fixed[0].message.latitude < fixed[-1].message.latitude


def test_bad_play_input_is_one_line(tmp_path, dds, monkeypatch, capsys):
    files = tiny_images(tmp_path / "img", 3)
    bag = write_bag(tmp_path / "drive", files, *fixes(3), ros1=False)
    for args, said in [((tmp_path / "nowhere",), "nowhere: not a ROS bag"),
                       ((bag, "--frames", "5:9"), "--frames 5:9: "),
                       ((bag, "--topic", "/nope"), "no image topic /nope"),
                       ((bag, "--rate", "0"), "--rate")]:
        code, _, err = run_cli(monkeypatch, capsys, "play", *args, "--wait", "0")
        assert code == 2 and len(error_lines(err)) == 1 and said in error_lines(err)[0], err


def test_the_node_publishes_the_loops_seqvpr_loops_finds_and_keeps_its_past_in_the_state(drive, shared_data,
                                                                                          dds, tmp_path):
    """The first half of Gardens Point's day walk then of its night walk as one bag (the night half revisits the day
    half): the node's published loop closures are the accepted rows of ``seqvpr loops`` on the same bag, and its
    state holds the drive so far."""
    root, _ = drive
    images = [p for side in ("day_left", "night_right")
              for p in sorted((shared_data / "gardenspoint_walking" / side).glob("*.jpg"))[:100]]
    write_bag(tmp_path / "revisit", images, *fixes(len(images)), ros1=False, compressed=True)
    seqvpr("loops", tmp_path / "revisit", "--exclude", "50f", "--threshold", "0.02", "--out", tmp_path / "loops")
    with open(tmp_path / "loops" / "loops.csv", newline="") as handle:
        accepted = [(int(r["frame"]), int(r["match"])) for r in csv.DictReader(handle) if r["accepted"] == "1"]
    assert len(accepted) >= 5
    loops, state = Recorder("/seqvpr/loop", STATUS), tmp_path / "node.npz"
    node = start_seqvpr(dds, "node", "--map", root / "map", *NODE, "--no-drop", "--loops", "--loop-exclude", "50f",
                        "--loop-threshold", "0.02", "--state", state)
    try:
        subprocess.run([sys.executable, "-m", "seqvpr.cli", "play", tmp_path / "revisit", "--rate", "20", "--wait",
                        "30"], env=dds, cwd=ROOT, check=True, capture_output=True, timeout=300)
        published = [status_values(s.message) for s in loops.wait_for(len(accepted), 120)]
        time.sleep(1.0)  # nothing more comes
    finally:
        _, err = stop(node)
        loops.close()
    assert [(int(v["frame"]), int(v["match"])) for v in published] == accepted
    assert all(s.message.status[0].name == "seqvpr loop" for s in loops.samples)
    assert len(loops.samples) == len(accepted) and f"{len(accepted)} loop closures published" in err
    with np.load(tmp_path / "node.loops.npz", allow_pickle=False) as saved:
        assert len(saved["rows"]) == len(images) and len(saved["stamps"]) == len(images)


@pytest.mark.parametrize("kept", ["sources", "map"])
def test_the_node_publishes_each_matched_map_frames_thumbnail_and_a_latched_route(drive, shared_data, dds,
                                                                                   tmp_path, kept):
    """A map of Gardens Point's day walk (a metre a frame), the first half of the night walk played: while localised
    or uncertain, the node publishes the matched map frame's thumbnail, byte for byte what the status names: made
    from the map's source images (a map of image files), or kept in the map (a map of the day bag built with
    --thumbnails: its frames are no files); the route reaches a late subscriber; the recording opens in the
    viewer."""
    import shutil

    from seqvpr.maps.thumbnails import map_thumbnail
    from seqvpr.ros2.dds import LATCHED
    from seqvpr.ros2.messages import COMPRESSED, PATH

    root, _ = drive
    if kept == "sources":
        day = tmp_path / "day"
        shutil.copytree(shared_data / "gardenspoint_walking" / "day_left", day)
        names = sorted(p.name for p in day.glob("*.jpg"))
        (day / "positions.csv").write_text("name,easting,northing\n" + "".join(f"{n},0,{i}\n"
                                                                                for i, n in enumerate(names)))
        seqvpr("map", "build", day, "--out", tmp_path / "map")
    else:
        seqvpr("map", "build", root / "day_left", "--thumbnails", "--out", tmp_path / "map")
    statuses, images = Recorder("/seqvpr/status", STATUS), Recorder("/seqvpr/match/compressed", COMPRESSED)
    node = start_seqvpr(dds, "node", "--map", tmp_path / "map", *NODE, "--no-drop", "--publish-images")
    try:
        played = subprocess.run([sys.executable, "-m", "seqvpr.cli", "play", root / "night_right", "--rate", "20",
                                 "--wait", "30", "--frames", "0:100", "--record", tmp_path / "rec"], env=dds, cwd=ROOT,
                                check=True, capture_output=True, text=True, timeout=300)
        got = [status_values(s.message) for s in statuses.wait_for(100, 120)]
        shown = [v for v in got if v["state"] in ("localised", "uncertain")]
        published = images.wait_for(len(shown), 60)
        route = Recorder("/seqvpr/route", PATH, profile=LATCHED)  # joins after the node published it
        paths = route.wait_for(1, 30)
        route.close()
    finally:
        stop(node)
        statuses.close()
        images.close()
    assert len(shown) > 10 and len(published) == len(shown)
    for values, sample in zip(shown, published):
        row = int(values["map_index"] or values["best_index"])
        expected = map_thumbnail(tmp_path / "map", row) if kept == "map" else Path(values["match_image"]).read_bytes()
        assert bytes(sample.message.data) == expected and sample.message.format == "jpeg"
        assert values["match_image"] == (f"thumbnails.bin[{row}]" if kept == "map" else values["match_image"])
    assert len(paths) == 1 and len(paths[0].message.poses) == 200
    if kept == "sources":
        assert [p.pose.position.y for p in paths[0].message.poses] == list(map(float, range(200)))
    # the recording (seqvpr play --record) opens in seqvpr view as a localisation: its statuses, in order
    assert "on /seqvpr/status" in played.stdout and "on /seqvpr/match/compressed" in played.stdout
    from seqvpr.viewer.runs import read_views

    view = read_views([tmp_path / "rec"])
    assert view.kind == "localize" and len(view.reference.names) == 200
    recorded = view.stream["rows"]
    assert 90 <= len(recorded) <= 100
    column = view.stream["columns"].index("state")
    assert [r[column] for r in recorded] == [v["state"] for v in got[: len(recorded)]]
