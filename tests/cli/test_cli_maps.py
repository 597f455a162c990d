"""``seqvpr map build``, ``seqvpr map info`` and ``seqvpr match --map`` as a user runs them."""

from __future__ import annotations

import json

import pytest

from tests.helpers import run_cli, write_route_files


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = write_route_files(tmp_path_factory.mktemp("route"), 100, 16, 5)
    return folder


def test_build_info_and_match_give_the_direct_predictions(route, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")
    assert code == 0, err
    assert "100 frames from 1 source(s), 16-D file descriptors, float32" in out
    code, out, _ = run_cli(monkeypatch, capsys, "map", "info", tmp_path / "m")
    assert code == 0 and "count:           100" in out and "positions, timestamps" in out
    assert "crs:             local" in out  # a traversal file's positions, without a zone
    code, out, _ = run_cli(monkeypatch, capsys, "map", "info", tmp_path / "m", "--json")
    assert json.loads(out)["dim"] == 16
    for length in ("1", "5"):
        common = ("-q", route / "qry.npz", "-L", length, "--radius", "10m")
        code, out, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "m", *common, "--out", tmp_path / "a")
        assert code == 0, err
        code, direct, err = run_cli(monkeypatch, capsys, "match", "-r", route / "ref.npz", *common,
                                    "--out", tmp_path / "b")
        assert code == 0, err
        assert (tmp_path / "a" / "predictions.csv").read_text() == (tmp_path / "b" / "predictions.csv").read_text()
        table = lambda text: [line for line in text.splitlines()[4:]  # noqa: E731 - the recall table, not the paths
                              if not line.startswith(("predictions:", "correspondences:"))]
        assert table(out) == table(direct)
        run = json.loads((tmp_path / "a" / "run.json").read_text())
        assert run["settings"]["map"] == str(tmp_path / "m") and run["settings"]["descriptor"] == "file"


@pytest.mark.parametrize("args, message", [
    (("-r", "REF", "--map", "MAP"), "give the reference as --reference or as --map (one of them)"),
    (("--map", "MAP", "--descriptor", "resnet18"), "--descriptor resnet18 differs from the map's file descriptors"),
    (("--map", "MAP", "--pca-dim", "4"), "--pca-dim does not apply to --map"),
    (("--map", "NOMAP"), "not a seqvpr map (no map.json"),
])
def test_bad_map_options_are_one_line_with_exit_2(route, tmp_path, monkeypatch, capsys, args, message):
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")
    assert code == 0
    (tmp_path / "half").mkdir()  # a half-built map: no map.json
    names = {"REF": route / "ref.npz", "MAP": tmp_path / "m", "NOMAP": tmp_path / "half"}
    code, out, err = run_cli(monkeypatch, capsys, "match", *[names.get(a, a) for a in args], "-q", route / "qry.npz",
                             "--radius", "10m", "--out", tmp_path / "o")
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_a_bad_source_leaves_no_map_folder(route, tmp_path, monkeypatch, capsys):
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", tmp_path / "nope.npy",
                           "--out", tmp_path / "m")
    assert code == 2 and "nope.npy: no such file" in err and not (tmp_path / "m").exists()


def test_index_and_shortlisted_match_report_the_shortlist_recall(route, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m",
                             "--index", "hnsw:8")
    assert code == 0 and "index hnsw:8 over frames (100 rows)" in out, err
    code, out, _ = run_cli(monkeypatch, capsys, "map", "index", tmp_path / "m", "--index", "flat")
    assert code == 0 and "index flat over frames (100 rows)" in out
    code, out, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "m", "-q", route / "qry.npz", "-L", "5",
                             "--radius", "10m", "--shortlist", "100", "--shortlist-history", "4", "--out", tmp_path / "s")
    assert code == 0 and "shortlist: 1.000 of the scored queries" in err
    run = json.loads((tmp_path / "s" / "run.json").read_text())["settings"]
    assert run["shortlist"] == {"per_frame": 100, "history": 4, "index": "flat", "nprobe": 16, "recall": 1.0}


@pytest.mark.parametrize("args, message", [
    (("-r", "REF", "--shortlist", "5"), "--shortlist S needs S >= 0 and a --map"),
    (("--map", "MAP", "--shortlist-history", "5"), "--shortlist-history H needs H >= 0 and a --shortlist"),
    (("--map", "MAP", "--shortlist", "5", "--shortlist-history", "-1"), "'--shortlist-history': -1 is not in [0, inf]"),
    (("--map", "MAP", "--shortlist", "5"), "has no index: add one with seqvpr map index"),
    (("--map", "MAP", "--shortlist", "5", "--method", "delta"), "applies to the frame-matching methods"),
])
def test_bad_shortlists_are_one_line(route, tmp_path, monkeypatch, capsys, args, message):
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m")[0] == 0
    names = {"REF": route / "ref.npz", "MAP": tmp_path / "m"}
    code, _, err = run_cli(monkeypatch, capsys, "match", *[names.get(a, a) for a in args], "-q", route / "qry.npz",
                           "--radius", "10m", "-L", "5", "--out", tmp_path / "o")
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_a_bad_index_spec_fails_before_the_build(route, tmp_path, monkeypatch, capsys):
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", tmp_path / "m",
                           "--index", "ivf:abc")
    assert code == 2 and "expected auto, flat, hnsw:M or ivf:NLIST" in err and not (tmp_path / "m").exists()


def test_an_image_map_describes_the_query_with_the_maps_backbone(tmp_path, monkeypatch, capsys):
    """A map of images through a backbone: the query images go through the same extractor settings (read back
    from map.json), so match --map equals the direct match."""
    from seqvpr.synthetic.world import write_demo_world

    # one thread count for both commands: each command chooses its own from the cores free at its start, and a
    # convolution summed over another count of threads differs in the last bits (seen under xdist's load)
    monkeypatch.setenv("SEQVPR_THREADS", "1")
    world = write_demo_world(tmp_path / "world", frames=20, width=64, height=48, seed=1, query_condition="dusk")
    describe = ("--descriptor", "efficientnet-lite0", "--image-size", "64x48", "--weights", "imagenet")
    code, out, err = run_cli(monkeypatch, capsys, "map", "build", world["test_reference"], *describe,
                             "--out", tmp_path / "m")
    assert code == 0 and "efficientnet-lite0 descriptors" in out, err
    common = ("-q", world["test_query"], "-L", "3", "--radius", "10m")
    assert run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "m", *common, "--out", tmp_path / "a")[0] == 0
    code, _, err = run_cli(monkeypatch, capsys, "match", "-r", world["test_reference"], *common, *describe,
                           "--out", tmp_path / "b")
    assert code == 0, err
    assert (tmp_path / "a" / "predictions.csv").read_text() == (tmp_path / "b" / "predictions.csv").read_text()


def test_a_map_folder_keeps_its_calibration_and_its_users_files_through_every_map_command(tmp_path, monkeypatch,
                                                                                             capsys):
    """After ``map index`` (the map's identity unchanged) ``localize`` still uses the calibrated threshold; a user's
    file and folder in the map folder survive build, index, check, info and shard."""
    (tmp_path / "route").mkdir()
    route = write_route_files(tmp_path / "route", 120, 16, 7)
    folder = tmp_path / "m"
    assert run_cli(monkeypatch, capsys, "map", "build", route / "ref.npz", "--out", folder)[0] == 0
    (folder / "notes.txt").write_text("mine")
    (folder / "drives").mkdir()
    (folder / "drives" / "a.txt").write_text("also mine")
    common = ("localize", "--map", folder, "-q", route / "qry.npz", "--radius", "10m", "--json")
    code, _, err = run_cli(monkeypatch, capsys, *common, "--calibrate", "--target-precision", "0.9", "--out",
                           tmp_path / "c")
    assert code == 0, err
    calibrated = json.loads((folder / "localizer.json").read_text())["calibrations"][0]["threshold"]
    for command in (("map", "index", folder, "--index", "flat"), ("map", "build", route / "ref.npz", "--out", folder),
                    ("map", "check", folder), ("map", "info", folder),
                    ("map", "shard", folder, "--shards", "2", "--out", tmp_path / "s")):
        code, _, err = run_cli(monkeypatch, capsys, *command)
        assert code == 0, (command, err)
        assert (folder / "notes.txt").read_text() == "mine" and (folder / "drives" / "a.txt").read_text() == "also mine"
        code, out, err = run_cli(monkeypatch, capsys, *common, "--out", tmp_path / "l")
        summary = json.loads(out)
        assert code == 0 and summary["threshold"] == calibrated, (command, err)
        assert summary["threshold_source"].startswith("calibrated on "), (command, summary["threshold_source"])
