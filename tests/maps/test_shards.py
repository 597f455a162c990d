"""Sharded maps: the shards tile the map, and matching them (one process, or two torchrun ranks) gives exactly what
matching the whole map gives, windows across shard edges included; a failing rank fails the run, leaving nothing."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from seqvpr.data.sources import load_traversal
from seqvpr.maps import build_map, match_map
from seqvpr.maps.files import open_sharded_map
from seqvpr.maps.sharding import shard_map, shard_ranges
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from tests.helpers import examples, raises_one_line, run_cli, write_route_files


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """A 240-frame map in two segments (two sources), and its query."""
    folder = tmp_path_factory.mktemp("shards")
    write_route_files(folder, n_frames=240, dim=24, seed=5)
    (folder / "a").mkdir()
    write_route_files(folder / "a", n_frames=90, dim=24, seed=6)
    build_map([str(folder / "ref.npz"), str(folder / "a" / "ref.npz")], folder / "map")
    return folder


@settings(max_examples=examples(40), deadline=None)
@given(count=st.integers(1, 500), shards=st.integers(1, 9), overlap=st.integers(0, 40))
def test_shards_own_equal_runs_that_tile_the_map_and_store_overlap_beyond_them(count, shards, overlap):
    if shards > count:
        raises_one_line("shards must be between 1", shard_ranges, count, shards, overlap)
        return
    ranges = shard_ranges(count, shards, overlap)
    assert [a for _, a, _, _ in ranges] == [0, *[b for _, _, b, _ in ranges[:-1]]] and ranges[-1][2] == count
    sizes = [b - a for _, a, b, _ in ranges]
    assert max(sizes) - min(sizes) <= 1
    for lo, a, b, hi in ranges:
        assert lo == max(0, a - overlap) and hi == min(count, b + overlap)


@pytest.mark.parametrize("method, length, velocities, shards, overlap", [
    ("matching", 5, (1.0,), 3, 4),          # the minimum overlap for L = 5
    ("matching", 9, (0.8, 1.0, 1.2), 4, 10),  # a velocity sweep spans 11 frames
    ("adaptive", 6, (1.0,), 5, 10),
    ("adaptive", 5, (1.0,), 3, 8),          # the minimum for paths of steps up to 2: 2 (L - 1) + 1 frames
    ("seqslam", 7, (1.0,), 2, 30),
    ("seqslam", 5, (1.0,), 4, 10),          # the minimum with the contrast neighbourhood: 5 + 10 // 2 + 1 frames
    ("single", 1, (1.0,), 7, 0),
    ("smoothing", 5, (1.0,), 3, 4),
])
def test_a_sharded_match_is_the_whole_maps(whole, tmp_path, method, length, velocities, shards, overlap):
    sharded = shard_map(whole / "map", tmp_path / "sharded", shards, overlap)
    query = load_traversal(str(whole / "qry.npz"), "query")
    settings_ = MatchSettings(SequenceSpec(length, velocities=velocities), k=15)
    expected = match_map(load_map_of(whole), query, method, settings_)
    got = match_map(sharded, query, method, settings_)
    np.testing.assert_array_equal(got.topk.indices, expected.topk.indices)
    np.testing.assert_allclose(got.topk.distances, expected.topk.distances, rtol=1e-6)
    np.testing.assert_array_equal(got.topk.has_window, expected.topk.has_window)
    np.testing.assert_array_equal(got.reference.segment_ids, expected.reference.segment_ids)
    np.testing.assert_array_equal(got.reference.descriptors[:], np.asarray(expected.reference.descriptors))
    if expected.correspondences is not None:
        for a, b in zip(got.correspondences, expected.correspondences):
            np.testing.assert_array_equal(a, b)
    edges = [r.own_first for r in sharded.shards[1:]]
    straddling = [e for e in edges if np.isin(expected.topk.indices[:, 0], np.arange(e - length, e + length)).any()]
    assert straddling or shards == 1 or length == 1  # windows across a shard edge were among the matches


def load_map_of(folder: Path):
    from seqvpr.maps import open_map

    return open_map(folder / "map")


def test_methods_a_shard_cannot_score_and_windows_longer_than_the_overlap_are_one_line(whole, tmp_path):
    sharded = shard_map(whole / "map", tmp_path / "sharded", 3, 4)
    query = load_traversal(str(whole / "qry.npz"), "query")
    for method in ("hmm", "graph", "hvpr"):
        raises_one_line("a sharded map is matched by", match_map, sharded, query, method,
                        MatchSettings(SequenceSpec(1 if method != "hvpr" else 5), k=5))
    for method in ("seqslam-cone", "seqslam-hybrid"):
        raises_one_line("best match over the whole map", match_map, sharded, query, method,
                        MatchSettings(SequenceSpec(5), k=5))
    raises_one_line("overlap by 4 frames, so windows may span at most 5; this match needs 6",
                    match_map, sharded, query, "matching", MatchSettings(SequenceSpec(6), k=5))
    for method, needs in (("adaptive", 9), ("seqslam", 11)):  # the frames their scores read, not only L
        raises_one_line(f"this match needs {needs} (shard it again with overlap {needs - 1})",
                        match_map, sharded, query, method, MatchSettings(SequenceSpec(5), k=5))
    (tmp_path / "sharded" / "shards.json").write_text('{"format": "seqvpr-sharded-map", "version": 1}')
    raises_one_line("malformed sharded map description", open_sharded_map, tmp_path / "sharded")


def test_map_shard_and_match_on_the_command_line_give_the_whole_maps_predictions(whole, tmp_path, monkeypatch,
                                                                                 capsys):
    code, out, err = run_cli(monkeypatch, capsys, "map", "shard", whole / "map", "--shards", "3", "--overlap", "9",
                             "--out", tmp_path / "s")
    assert code == 0, err
    assert "shard-001: rows 110..219 (stored from 101, overlap 9)" in out
    common = ("-q", whole / "qry.npz", "-L", "5", "--radius", "10m", "--method", "adaptive")
    code, _, err = run_cli(monkeypatch, capsys, "match", "--map", whole / "map", *common, "--out", tmp_path / "a")
    assert code == 0, err
    code, _, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "s", *common, "--out", tmp_path / "b")
    assert code == 0, err
    for name in ("predictions.csv", "correspondences.csv"):
        assert (tmp_path / "a" / name).read_text() == (tmp_path / "b" / name).read_text()


def torchrun(args, cwd: Path) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node 2 seqvpr ARGS`` as a user launches it (the same command alone runs
    in-process, by ``run_cli``)."""
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    launcher = [str(bin_dir / "torchrun"), "--standalone", "--nproc-per-node", "2"]
    command = [*launcher, shutil.which("seqvpr", path=env["PATH"]), *map(str, args)]
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def stream_columns(run: Path) -> list[list[str]]:
    """A localize run's stream.csv without its latency columns: what must be the same frame by frame."""
    return [line.split(",")[:11] for line in (run / "stream.csv").read_text().splitlines()]


@pytest.mark.slow
def test_two_torchrun_ranks_give_the_single_process_predictions_and_a_failing_rank_fails_the_run(whole, tmp_path,
                                                                                                monkeypatch, capsys):
    shard_map(whole / "map", tmp_path / "s", 3, 9)
    common = ["-q", whole / "qry.npz", "-L", "5", "--radius", "10m"]
    done = torchrun(["match", "--map", tmp_path / "s", *common, "--out", tmp_path / "two"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    code, _, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "s", *common, "--out", tmp_path / "one")
    assert code == 0, err
    assert (tmp_path / "two" / "predictions.csv").read_text() == (tmp_path / "one" / "predictions.csv").read_text()
    assert '"ranks": 2' in (tmp_path / "two" / "run.json").read_text()
    shard = tmp_path / "s" / "shard-002" / "descriptors.npy"
    np.save(shard, np.load(shard)[:10])  # the shard rank 0 matches second is damaged
    failed = torchrun(["match", "--map", tmp_path / "s", *common, "--out", tmp_path / "bad"], tmp_path)
    assert failed.returncode != 0 and "shard-002/descriptors.npy" in failed.stderr
    assert not (tmp_path / "bad").exists()


def test_open_map_opens_a_sharded_map_whole_so_the_localizer_and_map_info_take_one(whole, tmp_path, monkeypatch,
                                                                                   capsys):
    from seqvpr.localization import Localizer
    from seqvpr.localization.replay import replay
    from seqvpr.maps import open_map

    shard_map(whole / "map", tmp_path / "s", 4, 7)
    one, many = open_map(whole / "map"), open_map(tmp_path / "s")
    assert many.info.count == one.info.count and many.info.sources == one.info.sources
    np.testing.assert_array_equal(many.descriptors[17:200:3], np.asarray(one.descriptors[17:200:3]))
    query = load_traversal(str(whole / "qry.npz"), "query")
    for options in ({"seq_len": 5, "k": 5}, {"method": "hmm", "k": 5}):
        a, b = replay(Localizer.open(one, **options), query), replay(Localizer.open(many, **options), query)
        np.testing.assert_array_equal(a.indices, b.indices)
    code, out, err = run_cli(monkeypatch, capsys, "map", "info", tmp_path / "s")
    assert code == 0 and f"count:           {one.info.count}" in out, err


@pytest.mark.slow
def test_a_localizer_on_two_torchrun_ranks_over_a_sharded_map_streams_the_single_process_estimates(whole, tmp_path,
                                                                                                   monkeypatch, capsys):
    shard_map(whole / "map", tmp_path / "s", 2, 9)
    common = ["-q", whole / "qry.npz", "--radius", "10m", "-L", "5"]
    done = torchrun(["localize", "--map", tmp_path / "s", *common, "--out", tmp_path / "two"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    code, _, err = run_cli(monkeypatch, capsys, "localize", "--map", whole / "map", *common, "--out", tmp_path / "one")
    assert code == 0, err
    assert stream_columns(tmp_path / "two") == stream_columns(tmp_path / "one")  # status, score, estimate, best frame
    refused = torchrun(["localize", "--map", tmp_path / "s", *common, "--method", "hmm", "--out", tmp_path / "f"],
                       tmp_path)
    assert refused.returncode != 0 and "a sharded map is matched by" in refused.stderr
    assert not (tmp_path / "f").exists()


@pytest.fixture(scope="module")
def indexed(whole, tmp_path_factory):
    """The whole map with a flat index over its frames (a copy: the module's map stays index-free)."""
    from seqvpr.maps.index import add_index, parse_index_spec

    folder = tmp_path_factory.mktemp("indexed") / "map"
    shutil.copytree(whole / "map", folder)
    add_index(load_map_of(folder.parent), parse_index_spec("flat"))
    return folder


@pytest.mark.parametrize("method, length, history, over, shards", [
    ("matching", 5, 0, "frames", 3),
    ("matching", 7, 3, "frames", 4),   # history: the frames before each window place candidates too
    ("single", 1, 0, "frames", 5),
    ("matching", 5, 0, "smoothing:5", 3),  # an index over windows: each query window finds its candidates
])
def test_a_shortlisted_sharded_match_is_the_whole_maps_with_flat_indexes(whole, indexed, tmp_path, method, length,
                                                                         history, over, shards):
    from seqvpr.maps import open_map
    from seqvpr.maps.index import add_index, parse_index_spec

    source = indexed
    if over != "frames":
        source = tmp_path / "windows"
        shutil.copytree(indexed, source)
        add_index(open_map(source), parse_index_spec("flat"), windows=5, method="smoothing")
    sharded = shard_map(source, tmp_path / "s", shards, 8)  # each shard gets an index like the map's
    assert {sharded.open_shard(n).info.index["over"] for n in range(shards)} == {over}
    query = load_traversal(str(whole / "qry.npz"), "query")
    settings_ = MatchSettings(SequenceSpec(length), k=10)
    options = {"shortlist": 4, "history": history}
    expected = match_map(open_map(source), query, method, settings_, **options)
    got = match_map(sharded, query, method, settings_, **options)
    np.testing.assert_array_equal(got.shortlist.indices, expected.shortlist.indices)
    np.testing.assert_array_equal(got.topk.indices, expected.topk.indices)
    np.testing.assert_allclose(got.topk.distances, expected.topk.distances, rtol=1e-6)
    np.testing.assert_array_equal(got.topk.has_window, expected.topk.has_window)
    exact = match_map(sharded, query, method, settings_)
    assert (got.topk.indices[:, 0] != exact.topk.indices[:, 0]).any() or length == 1  # a shortlist, not exact


@pytest.mark.slow
def test_shortlisting_a_sharded_map_on_the_command_line_and_two_torchrun_ranks(whole, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, "map", "shard", whole / "map", "--shards", "3", "--overlap", "9",
                             "--out", tmp_path / "s")
    assert code == 0, err
    common = ("-q", whole / "qry.npz", "-L", "5", "--radius", "10m", "--shortlist", "3")
    code, _, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "s", *common, "--out", tmp_path / "no")
    assert code == 2 and err.count("\n") == 1 and f"shard-000 has no index: index every shard with seqvpr map index {tmp_path / 's'} --index SPEC" in err
    assert not (tmp_path / "no").exists()
    indexed = torchrun(["map", "index", tmp_path / "s", "--index", "flat"], tmp_path)  # each rank its shards'
    assert indexed.returncode == 0, indexed.stderr[-2000:]
    assert [line.split(":")[0] for line in indexed.stdout.splitlines()] == ["shard-000", "shard-001", "shard-002"]
    code, out, err = run_cli(monkeypatch, capsys, "map", "info", tmp_path / "s")
    assert code == 0, err
    assert "shards:          3, overlap 9" in out
    assert "  shard-001: rows 110..219 (stored from 101), index flat over frames" in out
    shutil.copytree(whole / "map", tmp_path / "m")
    code, _, err = run_cli(monkeypatch, capsys, "map", "index", tmp_path / "m", "--index", "flat")
    assert code == 0, err
    code, _, err = run_cli(monkeypatch, capsys, "match", "--map", tmp_path / "m", *common, "--out", tmp_path / "a")
    assert code == 0, err
    done = torchrun(["match", "--map", tmp_path / "s", *common, "--out", tmp_path / "two"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "two" / "predictions.csv").read_text() == (tmp_path / "a" / "predictions.csv").read_text()
    assert '"recall"' in (tmp_path / "two" / "run.json").read_text()  # the shortlist's recall, as for one map


@pytest.mark.slow
def test_a_localizer_shortlisting_a_sharded_map_streams_the_whole_maps_even_past_the_overlap(
        whole, indexed, tmp_path, monkeypatch, capsys):
    from seqvpr.localization import Localizer
    from seqvpr.localization.replay import replay
    from seqvpr.maps import open_map

    shard_map(indexed, tmp_path / "s", 4, 6)  # indexed like the map: flat, over frames
    query = load_traversal(str(whole / "qry.npz"), "query")
    # the candidates' windows are read through the shards, so a window wider than the overlap is re-ranked too
    for options in ({"seq_len": 5, "k": 5, "shortlist": 3}, {"seq_len": 7, "k": 3, "shortlist": 2, "history": 4},
                    {"seq_len": 8, "k": 3, "shortlist": 3}):
        a = replay(Localizer.open(open_map(indexed), **options), query)
        b = replay(Localizer.open(open_map(tmp_path / "s"), **options), query)
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_array_equal(a.score, b.score)
        np.testing.assert_array_equal(a.distances, b.distances)
    shard_map(whole / "map", tmp_path / "bare", 2, 6)  # shards of a map without an index have none
    raises_one_line("shard-000 has no index: index every shard with seqvpr map index", Localizer.open,
                    open_map(tmp_path / "bare"), seq_len=5, shortlist=3)
    common = ["-q", whole / "qry.npz", "--radius", "10m", "-L", "5", "--shortlist", "3"]
    done = torchrun(["localize", "--map", tmp_path / "s", *common, "--out", tmp_path / "two"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    code, _, err = run_cli(monkeypatch, capsys, "localize", "--map", indexed, *common, "--out", tmp_path / "one")
    assert code == 0, err
    assert stream_columns(tmp_path / "two") == stream_columns(tmp_path / "one")


@pytest.mark.parametrize("storage", ["float32", "sq8", "pq:4"])
def test_map_build_shards_writes_what_map_shard_of_the_built_map_writes_and_no_whole_map(whole, tmp_path, monkeypatch,
                                                                                        capsys, storage):
    """Shards written straight from the sources (no map of all the rows is ever written, checked at the one writer
    of map folders) are the shards of the built map, bit for bit: their identities and the whole map's, composed
    from the digests its files would have."""
    from seqvpr.maps import files, sharding

    sources = (whole / "ref.npz", whole / "a" / "ref.npz")
    written = []
    monkeypatch.setattr(sharding, "write_map", lambda folder, frames, *a: written.append(len(frames))
                        or files.write_map(folder, frames, *a))
    code, out, err = run_cli(monkeypatch, capsys, "map", "build", *sources, "--index", "flat", "--shards", "3",
                             "--overlap", "9", "--dtype", storage, "--out", tmp_path / "built")
    assert code == 0, err
    assert written == [119, 128, 119]  # 110 frames owned, 9 past each inner edge
    assert out.splitlines()[-4] == "sharded map: " + str(tmp_path / "built") + " (330 frames in 3 shards, overlap 9)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["built"]  # nothing else was written beside it
    build_map(list(map(str, sources)), tmp_path / "whole", dtype=storage)
    expected = shard_map(tmp_path / "whole", tmp_path / "split", 3, 9)
    built = open_sharded_map(tmp_path / "built")
    assert built.shards == expected.shards and built.count == expected.count
    assert built.info["identity"] == expected.info["identity"] and built.info["files"] == expected.info["files"]
    for number in range(3):
        a, b = built.open_shard(number), expected.open_shard(number)
        np.testing.assert_array_equal(np.asarray(a.descriptors), np.asarray(b.descriptors))
        assert a.info.index["spec"] == "flat" and a.info.index["ntotal"] == a.info.count
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", *sources, "--shards", "400", "--out", tmp_path / "x")
    assert code == 2 and "--shards must be between 1 and the map's 330 frames" in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["built", "split", "whole"]


def test_a_sharded_match_through_a_model_is_the_whole_maps(whole, tmp_path):
    import torch

    from seqvpr.models.registry import TrainedModel
    from seqvpr.sequences.descriptors import SeqNet

    sharded = shard_map(whole / "map", tmp_path / "sharded", 3, 4)
    query = load_traversal(str(whole / "qry.npz"), "query")
    torch.manual_seed(0)
    dim = query.descriptors.shape[1]
    models = {"seqnet": TrainedModel("seqnet", SeqNet(dim, dim, 3).eval(), 5, tmp_path / "seqnet")}
    settings_ = MatchSettings(SequenceSpec(5), k=10)
    expected = match_map(load_map_of(whole), query, "seqnet", settings_, models)
    got = match_map(sharded, query, "seqnet", settings_, models)
    np.testing.assert_array_equal(got.topk.indices, expected.topk.indices)
    np.testing.assert_allclose(got.topk.distances, expected.topk.distances, rtol=1e-5)


def test_each_shard_as_a_reference_owns_the_rows_its_record_gives_and_names_its_index(whole, indexed, tmp_path):
    sharded = shard_map(indexed, tmp_path / "s", 3, 5)
    for number, record in enumerate(sharded.shards):
        shard = sharded.open_shard(number)
        assert shard.owned == slice(record.own_first - record.first, record.own_last - record.first)
        assert shard.index["over"] == "frames" and len(shard) == shard.info.count
    whole_map = load_map_of(whole)
    assert whole_map.owned == slice(0, len(whole_map)) and whole_map.index is None
    assert whole_map.frames.owned == slice(0, len(whole_map)) and whole_map.frames.index is None


def test_the_old_sharded_match_name_warns_and_is_match_map(whole, tmp_path):
    from seqvpr.maps.shards import match_sharded_map

    sharded = shard_map(whole / "map", tmp_path / "sharded", 3, 4)
    query = load_traversal(whole / "qry.npz", "query")
    settings_ = MatchSettings(SequenceSpec(5), k=5)
    with pytest.warns(DeprecationWarning, match="use seqvpr.maps.match_map"):
        old = match_sharded_map(sharded, query, "matching", settings_)
    np.testing.assert_array_equal(old.topk.indices, match_map(sharded, query, "matching", settings_).topk.indices)
