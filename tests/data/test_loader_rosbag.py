"""Robot recordings: bags written here with ``rosbags`` itself (ROS 2 mcap and sqlite3, ROS 1), 30 frames of Gardens
Point Walking plus NavSatFix fixes, give the same Recall@K as the image folders they were made from. Bags of small
synthetic frames show that frames are read on demand (a one-frame replay decodes one frame), named by bag and
stamp, and that a map built from a bag outlives the frame cache and gives its fixes back as latitude/longitude."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.sources import load_traversal
from tests.helpers import raises_one_line, run_cli

from tests.bags import FRAMES, STEP_S, fixes, write_bag


def image_folder(src, dst, lat, lon):
    """The first FRAMES images of a Gardens Point side, with a positions.csv of the same fixes."""
    dst.mkdir()
    rows = ["image,lat,lon,timestamp"]
    for i, path in enumerate(sorted(src.glob("*.jpg"))[:FRAMES]):
        shutil.copy(path, dst / path.name)
        rows.append(f"{path.name},{lat[i]:.9f},{lon[i]:.9f},{i * STEP_S}")
    (dst / "positions.csv").write_text("\n".join(rows) + "\n")
    return dst


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


@pytest.mark.slow
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


def test_a_frame_cache_inside_the_bag_is_refused(walking, tmp_path, monkeypatch):
    """The bag frame cache is an output too: never inside (or holding) the bag it is made from."""
    _, sides = walking
    _, images, lat, lon = sides["day_left"]
    bag = write_bag(tmp_path / "b", images[:3], lat, lon, ros1=False)
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(bag / "frames"))
    raises_one_line("the bag frame cache ($SEQVPR_BAG_FRAMES)", load_traversal, bag, "reference")
    assert not (bag / "frames").exists()


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


def synthetic_jpegs(folder, n: int, seed: int = 0) -> list:
    """``n`` small different JPEG frames (48 x 32, smooth random colours)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    files = []
    for i in range(n):
        coarse = rng.integers(0, 255, (4, 6, 3), dtype=np.uint8)
        file = folder / f"{i:04d}.jpg"
        Image.fromarray(coarse).resize((48, 32), Image.BILINEAR).save(file, quality=90)
        files.append(file)
    return files


def counting_reads(monkeypatch) -> dict[str, int]:
    """Count every image file read (``read_image``, wherever it was imported) and every PIL decode (``Image.open``)."""
    import PIL.Image

    import seqvpr.data.images
    import seqvpr.features.extraction
    import seqvpr.features.patchnorm
    import seqvpr.localization.encoder

    counts = {"read_image": 0, "open": 0}
    read, open_ = seqvpr.data.images.read_image, PIL.Image.open

    def counted_read(*args, **kwargs):
        counts["read_image"] += 1
        return read(*args, **kwargs)

    def counted_open(*args, **kwargs):
        counts["open"] += 1
        return open_(*args, **kwargs)

    for module in (seqvpr.data.images, seqvpr.features.extraction, seqvpr.features.patchnorm,
                   seqvpr.localization.encoder):
        monkeypatch.setattr(module, "read_image", counted_read)
    monkeypatch.setattr(PIL.Image, "open", counted_open)
    return counts


def test_replaying_one_frame_of_a_200_frame_bag_decodes_one_frame(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    images = synthetic_jpegs(tmp_path / "jpg", 200)
    lat, lon = fixes(200)
    bag = write_bag(tmp_path / "long", images, lat, lon, ros1=False, compressed=True)
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", bag, "--out", tmp_path / "m")
    assert code == 0, err
    counts = counting_reads(monkeypatch)
    code, _, err = run_cli(monkeypatch, capsys, "localize", "--map", tmp_path / "m", "-q", bag, "--frames", "0:1",
                           "--out", tmp_path / "o")
    assert code == 0, err
    assert counts == {"read_image": 1, "open": 1}, counts
    stored = sorted((tmp_path / "cache" / "bag-frames").rglob("*.jpg"))  # each frame's JPEG bytes, as they are
    assert len(stored) == 200 and {f.read_bytes() for f in stored} == {f.read_bytes() for f in images}


def test_loading_a_bag_decodes_no_frame(tmp_path, monkeypatch):
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    images = synthetic_jpegs(tmp_path / "jpg", 20)
    bag = write_bag(tmp_path / "b", images, *fixes(20), ros1=False, compressed=True)
    counts = counting_reads(monkeypatch)
    traversal = load_traversal(bag, "query")
    assert counts == {"read_image": 0, "open": 0} and len(traversal) == 20
    assert traversal.image_paths[0].read_bytes() == images[0].read_bytes()


def test_raw_frames_are_stored_losslessly_and_named_by_bag_and_stamp(tmp_path, monkeypatch):
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    images = synthetic_jpegs(tmp_path / "jpg", 4)
    bag = write_bag(tmp_path / "r.bag", images, *fixes(4), ros1=True)
    traversal = load_traversal(f"{bag}:/camera/image_raw", "query")
    assert traversal.frame_names() == [f"{bag}:/camera/image_raw@{100 + 0.5 * i:.9f}" for i in range(4)]
    for file, image in zip(traversal.image_paths, images):
        assert file.suffix == ".png" and (tmp_path / "cache" / "bag-frames") in file.parents
        np.testing.assert_array_equal(np.asarray(Image.open(file)), np.asarray(Image.open(image).convert("RGB")))


def test_a_bag_map_names_its_frames_by_stamp_reports_its_topics_and_outlives_the_cache(tmp_path, monkeypatch, capsys):
    from seqvpr.localization import Localizer

    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    images = synthetic_jpegs(tmp_path / "jpg", 12)
    lat, lon = fixes(12)
    bag = write_bag(tmp_path / "run", images, lat[:10], lon[:10], ros1=False, compressed=True)  # 2 frames: no fix
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", bag, "--stamp-tolerance", "0.2", "--out",
                           tmp_path / "m")
    assert code == 0, err
    assert err.splitlines()[:3] == [f"seqvpr: {bag}?tolerance=0.2: camera topic /camera/image_raw",
                                f"seqvpr: {bag}?tolerance=0.2: position topic /gps/fix",
                                f"seqvpr: {bag}?tolerance=0.2: 2 frames without a position fix within 0.2 s "
                                "(left out)"]
    names = [f"{bag}:/camera/image_raw@{100 + 0.5 * i:.9f}" for i in range(10)]
    assert (tmp_path / "m" / "names.txt").read_text().splitlines() == names
    import shutil

    shutil.rmtree(tmp_path / "cache")
    code, out, err = run_cli(monkeypatch, capsys, "map", "info", tmp_path / "m")
    assert code == 0 and "count:           10" in out and "crs:             utm:56S" in out, err
    query = image_folder_with_fixes(tmp_path / "q", images[:10], lat, lon)
    code, out, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "m", "-q", query, "-L", "3",
                             "--radius", "2.5m", "--json", "--out", tmp_path / "o")
    assert code == 0 and json.loads(out)["recall"]["1"] == 1.0, err
    localizer = Localizer.open(tmp_path / "m", seq_len=1)
    estimate = localizer.update(images[4])
    assert estimate.name == names[4] and not (tmp_path / "cache" / "bag-frames").exists()


def image_folder_with_fixes(folder, images, lat, lon):
    """The images copied into ``folder`` with a positions.csv of latitude/longitude."""
    folder.mkdir()
    rows = ["name,lat,lon"]
    for i, image in enumerate(images):
        shutil.copy(image, folder / image.name)
        rows.append(f"{image.name},{lat[i]:.10f},{lon[i]:.10f}")
    (folder / "positions.csv").write_text("\n".join(rows) + "\n")
    return folder


@pytest.mark.parametrize("kind", ["bag", "image folder"])
def test_a_maps_positions_go_back_to_the_latitudes_and_longitudes_it_was_built_from(tmp_path, monkeypatch, capsys,
                                                                                     kind):
    from seqvpr.data.geo import utm_to_latlon
    from seqvpr.maps import open_map

    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "cache"))
    images = synthetic_jpegs(tmp_path / "jpg", 8)
    lat, lon = fixes(8)
    lat, lon = np.round(lat, 10), np.round(lon, 10)  # what the positions.csv holds
    source = (write_bag(tmp_path / "b", images, lat, lon, ros1=False, compressed=True) if kind == "bag"
              else image_folder_with_fixes(tmp_path / "f", images, lat, lon))
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", source, "--out", tmp_path / "m")
    assert code == 0, err
    saved = open_map(tmp_path / "m")
    assert saved.info.crs == saved.frames.crs == "utm:56S"
    back = utm_to_latlon(saved.frames.positions, saved.info.crs)
    np.testing.assert_allclose(back, np.c_[lat, lon], rtol=0, atol=1e-6)
    from seqvpr.localization import Localizer

    localizer = Localizer.open(tmp_path / "m", seq_len=1, threshold=0.0)  # every scored frame localised
    for i in (2, 5):
        estimate = localizer.update(images[i])
        assert estimate.index == i and estimate.latlon == pytest.approx((lat[i], lon[i]), abs=1e-6)
    code, _, err = run_cli(monkeypatch, capsys, "localize", "--map", tmp_path / "m", "-q", source, "-L", "1",
                           "--threshold", "0", "--radius", "5m", "--out", tmp_path / "o")
    assert code == 0, err
    rows = [r for r in csv.DictReader(open(tmp_path / "o" / "stream.csv")) if r["status"] == "localised"]
    assert len(rows) == 8
    for r in rows:
        row = int(r["localised_row"])
        assert (float(r["latitude"]), float(r["longitude"])) == pytest.approx((lat[row], lon[row]), abs=1e-6)


def test_an_unwritable_cache_folder_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    images = synthetic_jpegs(tmp_path / "jpg", 3)
    lat, lon = fixes(3)
    bag = write_bag(tmp_path / "b", images, lat, lon, ros1=False, compressed=True)
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "file" / "cache"))
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", bag, "--out", tmp_path / "m")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "cache folder" in err and "SEQVPR_CACHE" in err, err
    assert not (tmp_path / "m").exists()


def damaged_bags(tmp_path, monkeypatch) -> list:
    """A bag of each kind damaged as downloads and disks damage them: bad magic, cut short, unparsable or dangling
    metadata, its data file gone."""
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    images = synthetic_jpegs(tmp_path / "jpg", 6)
    ros1 = write_bag(tmp_path / "good.bag", images, *fixes(6), ros1=True)
    ros2 = write_bag(tmp_path / "good2", images, *fixes(6), ros1=False)
    made = []
    magic = tmp_path / "magic.bag"
    magic.write_bytes(b"#NOTABAG V9.9\n" + ros1.read_bytes()[14:])
    made.append(magic)
    for fraction in (0.1, 0.5, 0.9):
        cut = tmp_path / f"cut{fraction}.bag"
        data = ros1.read_bytes()
        cut.write_bytes(data[: int(len(data) * fraction)])
        made.append(cut)
    for name, text in (("yaml", "rosbag2_bagfile_information: [unclosed\n  : :"), ("keys", "nothing: here\n")):
        folder = tmp_path / f"bad-{name}"
        shutil.copytree(ros2, folder)
        (folder / "metadata.yaml").write_text(text)
        made.append(folder)
    gone = tmp_path / "gone"
    shutil.copytree(ros2, gone)
    for data in [*gone.glob("*.mcap"), *gone.glob("*.db3")]:
        data.unlink()
    made.append(gone)
    return made


def test_a_damaged_bag_is_one_line_wherever_it_is_read(tmp_path, monkeypatch):
    """Loading (match, extract, map build) and playing a damaged bag read it through one boundary: one line naming
    the bag, never a rosbags or YAML traceback."""
    from seqvpr.data.loaders.rosbag import BagTopics
    from seqvpr.ros2.play import play_bag

    for bag in damaged_bags(tmp_path, monkeypatch):
        raises_one_line(str(bag), load_traversal, str(bag), "query")
        raises_one_line(str(bag), play_bag, bag, BagTopics(), None, wait=0)
    raises_one_line("rate must be from", play_bag, tmp_path / "good.bag", BagTopics(), None, rate=1e-300)


def test_a_frames_folder_that_cannot_be_made_names_the_setting_that_chose_it(tmp_path, monkeypatch):
    images = synthetic_jpegs(tmp_path / "jpg", 3)
    bag = write_bag(tmp_path / "r.bag", images, *fixes(3), ros1=True)
    (tmp_path / "a-file").write_text("not a folder")
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "a-file" / "frames"))
    raises_one_line("point $SEQVPR_BAG_FRAMES at a writable folder", load_traversal, str(bag), "query")


def test_fixes_without_a_fix_or_off_the_globe_are_left_out_and_counted(tmp_path, monkeypatch, caplog):
    """A NavSatFix whose status says no fix (-1), or whose latitude/longitude are not finite or not on the globe,
    places no frame: left out with a counted warning, as frames without a fix are (was -73,646 km of easting)."""
    import logging

    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    images = synthetic_jpegs(tmp_path / "jpg", 8)
    lat, lon = fixes(8)
    lat[5], lon[6] = np.nan, 250.0
    bag = write_bag(tmp_path / "r.bag", images, lat, lon, ros1=True, statuses=[0, 0, -1, 0, -1, 0, 0, 0])
    with caplog.at_level(logging.WARNING, logger="seqvpr"):
        traversal = load_traversal(f"{bag}?tolerance=0.11", "query")
    assert "4 position fixes left out (1 not finite, 1 not on the globe, 2 status: no fix)" in caplog.text
    assert len(traversal) == 4 and traversal.frame_index.tolist() == [0, 1, 3, 7]
    from seqvpr.data.geo import latlon_to_utm

    good, _ = latlon_to_utm(*fixes(8), "fixes")
    np.testing.assert_allclose(traversal.positions, good[[0, 1, 3, 7]])


def test_repeated_header_stamps_keep_frame_names_unique_and_are_counted(tmp_path, monkeypatch, caplog):
    import logging

    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    images = synthetic_jpegs(tmp_path / "jpg", 4)
    bag = write_bag(tmp_path / "r.bag", images, *fixes(4), ros1=True, zero_stamps=True)
    with caplog.at_level(logging.WARNING, logger="seqvpr"):
        traversal = load_traversal(str(bag), "query")
    names = traversal.frame_names()
    assert len(set(names)) == 4 and names[1] == f"{bag}:/camera/image_raw@0.000000000#2"
    assert "3 camera frames repeat another frame's header stamp" in caplog.text
