"""The map's faiss index and shortlisted matching: specs, seeded builds, candidates against a plain loop, and a
shortlist as wide as the map equal to exhaustive matching."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.data.sources import load_traversal
from seqvpr.maps import build_map, open_map, match_map
from seqvpr.maps.index import (
    IndexSpec, add_index, auto_index_spec, open_frame_index, parse_index_spec, search_frames,
)
from seqvpr.maps.match import shortlist_recall
from seqvpr.evaluation.ground_truth import ground_truth
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.rerank import frame_shortlist
from seqvpr.sequences.windows import SequenceSpec, window_starts
from tests.helpers import examples, raises_one_line, write_route_files

SETTINGS = MatchSettings(SequenceSpec(5), k=10)


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = write_route_files(tmp_path_factory.mktemp("route"), 300, 16, 6)
    return folder


def test_index_specs_parse_and_bad_ones_are_one_line():
    assert parse_index_spec("flat") == IndexSpec("flat")
    assert parse_index_spec("hnsw:32") == IndexSpec("hnsw", m=32)
    assert parse_index_spec("IVF:1024,pq:32") == IndexSpec("ivf", nlist=1024, pq=32)
    assert str(parse_index_spec("ivf:64,pq:8")) == "ivf:64,pq:8"
    assert parse_index_spec("Auto") == IndexSpec("auto") and str(IndexSpec("auto")) == "auto"
    for bad in ("ivf", "hnsw:0", "ivf:16,pq", "pq:8", "lsh"):
        raises_one_line("expected auto, flat, hnsw:M or ivf:NLIST" if bad != "hnsw:0" else "at least 2",
                        parse_index_spec, bad)


@pytest.mark.parametrize("n, dim, expected", [
    (9_999, 256, "flat"), (10_000, 256, "ivf:128,pq:32"), (100_000, 256, "ivf:256,pq:32"),
    (1_000_000, 256, "ivf:1024,pq:32"), (10_000_000, 256, "ivf:1024,pq:32"), (1_000_000, 2048, "ivf:1024,pq:256"),
    (50_000, 100, "ivf:256,pq:10"), (50_000, 7, "ivf:256,pq:1"),
])
def test_auto_is_flat_for_small_maps_and_ivf_pq_without_the_vectors_for_large_ones(n, dim, expected):
    """About sqrt(N) lists (a power of two, at most 1,024: k-means stays minutes on two cores) and a PQ byte for
    every 8 dimensions, a divisor of the dimension."""
    spec = auto_index_spec(n, dim)
    assert str(spec) == expected
    assert spec.kind == "flat" or dim % spec.pq == 0


def test_an_interrupted_index_build_goes_on_from_its_last_save_and_gives_the_same_index(tmp_path, monkeypatch):
    """``map index`` saves its partial index beside the map (once trained, then every CHECKPOINT_ROWS rows); a run
    stopped part way (here: a failing add) and run again resumes there, and the index equals one built at once."""
    import faiss

    from seqvpr.maps import index as module

    rng = np.random.default_rng(0)
    rows = rng.standard_normal((3000, 16)).astype(np.float32)
    np.save(tmp_path / "rows.npy", rows)
    build_map([str(tmp_path / "rows.npy")], tmp_path / "map")
    build_map([str(tmp_path / "rows.npy")], tmp_path / "fresh")
    monkeypatch.setattr(module, "ADD_BLOCK", 256)
    monkeypatch.setattr(module, "CHECKPOINT_ROWS", 1024)
    spec = parse_index_spec("ivf:16,pq:4")
    whole = add_index(open_map(tmp_path / "fresh"), spec, seed=3)
    added, real_add = [], faiss.IndexIVFPQ.add

    def failing_add(index, block):
        added.append(len(block))
        if sum(added) > 2300:
            raise KeyboardInterrupt
        return real_add(index, block)

    monkeypatch.setattr(faiss.IndexIVFPQ, "add", failing_add)
    saved = open_map(tmp_path / "map")
    with pytest.raises(KeyboardInterrupt):
        add_index(saved, spec, seed=3)
    partial = module.partial_folder(saved)
    assert json.loads((partial / "progress.json").read_text())["rows"] == 2048  # the last save before the stop
    assert open_map(tmp_path / "map").info.index is None  # nothing committed
    monkeypatch.setattr(faiss.IndexIVFPQ, "add", real_add)
    ticks = []
    record = add_index(saved, spec, seed=3, progress=lambda total, what: (ticks.append(what), ticks.append)[1])
    assert "index ivf:16,pq:4 (resumed at row 2048)" in ticks and not partial.exists()
    resumed = faiss.serialize_index(open_frame_index(open_map(tmp_path / "map")))
    assert np.array_equal(resumed, faiss.serialize_index(open_frame_index(open_map(tmp_path / "fresh"))))
    assert record["spec"] == whole["spec"] == "ivf:16,pq:4"
    add_index(saved, spec, seed=4)  # another seed: a fresh build, no partial from before is used or left
    assert not partial.exists()


@settings(max_examples=examples(80), deadline=None)
@given(st.integers(1, 6), st.integers(1, 4), st.integers(8, 30), st.sampled_from(["centered", "causal"]),
       st.integers(0, 4), st.integers(0, 2**32 - 1))
def test_frame_shortlist_matches_a_plain_loop(length, width, n_reference, align, history, seed):
    rng = np.random.default_rng(seed)
    n_query = 12
    neighbors = rng.integers(-1, n_reference, size=(n_query, width))
    segments = np.sort(rng.integers(0, 3, n_query))
    spec = SequenceSpec(length, align)
    starts = window_starts(segments, length, spec.offset, "drop")
    got = frame_shortlist(neighbors, starts, spec, n_reference, history=history, query_segments=segments)
    for i in range(n_query):
        expected = set()
        if starts[i] >= 0:
            for k in range(-history, length):
                frame = starts[i] + k
                if frame < 0 or segments[frame] != segments[starts[i]]:
                    continue
                for r in neighbors[frame]:
                    c = r - k + spec.offset
                    if r >= 0 and 0 <= c < n_reference:
                        expected.add(int(c))
        row = got.indices[i]
        assert set(row[row >= 0].tolist()) == expected and len(row[row >= 0]) == len(expected)


def test_a_flat_shortlist_as_wide_as_the_map_is_exhaustive_matching(route, tmp_path):
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    add_index(saved, IndexSpec("flat"))
    saved = open_map(tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    exhaustive = match_map(saved, query, "matching", SETTINGS)
    shortlisted = match_map(saved, query, "matching", SETTINGS, shortlist=300)
    np.testing.assert_array_equal(shortlisted.topk.indices, exhaustive.topk.indices)
    np.testing.assert_allclose(shortlisted.topk.distances, exhaustive.topk.distances, rtol=1e-5)
    narrow = match_map(saved, query, "matching", SETTINGS, shortlist=3)
    gt = ground_truth(saved.frames, query)
    assert 0.5 < shortlist_recall(narrow, gt) <= shortlist_recall(shortlisted, gt) == 1.0
    carried = match_map(saved, query, "matching", SETTINGS, shortlist=3, history=6)  # a superset of the candidates
    for few, more in zip(narrow.shortlist.indices, carried.shortlist.indices):
        assert set(few[few >= 0]) <= set(more[more >= 0])
    assert shortlist_recall(narrow, gt) <= shortlist_recall(carried, gt)
    single = match_map(saved, query, "single", SETTINGS, shortlist=10)
    np.testing.assert_array_equal(single.topk.indices, match_map(saved, query, "single", SETTINGS).topk.indices)


def test_ivf_and_hnsw_indexes_are_saved_seeded_and_reopened(route, tmp_path):
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query").descriptors.astype(np.float32)
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    found = []
    for spec in ("ivf:8,pq:4", "ivf:8,pq:4", "hnsw:8"):
        record = add_index(saved, parse_index_spec(spec), seed=3)
        reopened = open_map(tmp_path / "m")
        assert reopened.info.index["spec"] == spec and record["ntotal"] == 300
        found.append(search_frames(open_frame_index(reopened, nprobe=8), query, 5)[0])
    np.testing.assert_array_equal(found[0], found[1])  # same seed, same index
    assert (found[2][:, 0] >= 0).all()


def test_shortlist_errors_are_one_line(route, tmp_path):
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    raises_one_line("has no index", match_map, saved, query, "matching", SETTINGS, shortlist=5)
    raises_one_line("applies to the frame-matching methods", match_map, saved, query, "seqgem", SETTINGS, shortlist=5)
    add_index(saved, IndexSpec("flat"), windows=5)
    raises_one_line("needs an index over frames", match_map, open_map(tmp_path / "m"), query, "matching", SETTINGS,
                    shortlist=5, history=3)
    add_index(saved, IndexSpec("flat"))
    (tmp_path / "m" / "index.faiss").write_bytes(b"garbage")
    raises_one_line("index.faiss: its content is not what", match_map, open_map(tmp_path / "m"), query, "matching", SETTINGS,
                    shortlist=5)
    raises_one_line("must divide the dimension 16", add_index, saved, IndexSpec("ivf", nlist=4, pq=5))
    raises_one_line("400 lists for 300 frames", add_index, saved, IndexSpec("ivf", nlist=400))


def test_a_float16_map_shortlists_like_the_float32_one(route, tmp_path):
    query = load_traversal(route / "qry.npz", "query")
    results = []
    for dtype in ("float32", "float16"):
        saved = build_map([str(route / "ref.npz")], tmp_path / dtype, dtype=dtype)
        add_index(saved, IndexSpec("flat"))
        results.append(match_map(open_map(tmp_path / dtype), query, "matching", SETTINGS, shortlist=20))
    assert (results[0].topk.indices[:, 0] == results[1].topk.indices[:, 0]).mean() > 0.95


@pytest.mark.parametrize("method", ["smoothing", "delta", "seqgem"])
def test_a_window_index_answers_retrieval_as_pooling_the_map_does(route, tmp_path, method):
    from tests.helpers import match_method

    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    record = add_index(saved, IndexSpec("flat"), windows=5, method=method)
    assert record["over"] == f"{method}:5" and (tmp_path / "m" / "index_rows.npy").is_file()
    saved = open_map(tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    indexed = match_map(saved, query, method, SETTINGS)
    reference = load_traversal(route / "ref.npz", "reference")
    direct = match_method(method, reference, query, SETTINGS)
    np.testing.assert_array_equal(indexed.topk.indices, direct.topk.indices)
    np.testing.assert_allclose(indexed.topk.distances, direct.topk.distances, rtol=1e-5, atol=1e-6)
    other_length = match_map(saved, query, method, replace(SETTINGS, sequence=SequenceSpec(3)))  # pools the map
    np.testing.assert_array_equal(other_length.topk.indices,
                                  match_method(method, reference, query, replace(SETTINGS, sequence=SequenceSpec(3)))
                                  .topk.indices)
    (tmp_path / "m" / "index_rows.npy").unlink()
    raises_one_line("index_rows.npy: missing", match_map, open_map(tmp_path / "m"), query, method, SETTINGS)


def test_a_window_index_as_wide_as_the_map_is_exhaustive_matching(route, tmp_path):
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    record = add_index(saved, IndexSpec("flat"), windows=5)
    assert record["over"] == "smoothing:5"
    saved = open_map(tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    exhaustive = match_map(saved, query, "matching", SETTINGS)
    np.testing.assert_array_equal(match_map(saved, query, "matching", SETTINGS, shortlist=300).topk.indices,
                                  exhaustive.topk.indices)
    narrow = match_map(saved, query, "matching", SETTINGS, shortlist=10)
    assert shortlist_recall(narrow, ground_truth(saved.frames, query)) > 0.8


def test_a_seqnet_window_index_answers_seqnet_retrieval_and_records_its_model(route, tmp_path):
    from tests.helpers import match_method
    from seqvpr.models.registry import load_trained_model
    from seqvpr.models.seqnet import save_seqnet
    from seqvpr.sequences.descriptors import SeqNet

    save_seqnet(tmp_path / "seqnet", SeqNet(16, 8, 3), {"sequence": {"length": 5}})
    save_seqnet(tmp_path / "other", SeqNet(16, 8, 3), {"sequence": {"length": 5}})
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    raises_one_line("needs its SeqNet (index_model)", add_index, saved, IndexSpec("flat"), windows=5,
                    method="seqnet")
    record = add_index(saved, IndexSpec("flat"), windows=5, method="seqnet", model_folder=tmp_path / "seqnet")
    assert record["dim"] == 8 and record["model"]["folder"] == str(tmp_path / "seqnet")
    saved = open_map(tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    models = {"seqnet": load_trained_model(tmp_path / "seqnet")}
    direct = match_method("seqnet", load_traversal(route / "ref.npz", "reference"), query, SETTINGS, models)
    indexed = match_map(saved, query, "seqnet", SETTINGS, models)
    np.testing.assert_array_equal(indexed.topk.indices, direct.topk.indices)
    shortlisted = match_map(saved, query, "matching", SETTINGS, shortlist=300)  # the index's SeqNet, from its folder
    np.testing.assert_array_equal(shortlisted.topk.indices, match_map(saved, query, "matching", SETTINGS).topk.indices)
    other = {"seqnet": load_trained_model(tmp_path / "other")}
    assert (match_map(saved, query, "seqnet", SETTINGS, other).topk.indices
            == match_method("seqnet", load_traversal(route / "ref.npz", "reference"), query, SETTINGS, other)
            .topk.indices).all()  # another SeqNet pools the map itself
    (tmp_path / "seqnet" / "model.safetensors").write_bytes(b"changed")
    raises_one_line("which is gone or has changed", match_map, saved, query, "matching", SETTINGS, shortlist=5)


def test_a_pq_index_re_ranks_its_candidates_on_the_maps_rows(tmp_path):
    """A PQ index's codes only approximate distances: its frames are searched REFINE times wider and re-ranked on
    the map's own rows, so with every list probed and every row a candidate the shortlist is the exact nearest
    frames (a brute-force loop), distances included; without the re-ranking PQ alone misses some."""
    from seqvpr.maps.index import REFINE, IndexNeighbors

    rng = np.random.default_rng(2)
    rows = rng.standard_normal((300, 16)).astype(np.float32)
    np.save(tmp_path / "rows.npy", rows)
    saved = build_map([str(tmp_path / "rows.npy")], tmp_path / "map")
    add_index(saved, parse_index_spec("ivf:4,pq:2"), seed=0)
    neighbors = IndexNeighbors(open_map(tmp_path / "map"), nprobe=4)
    assert neighbors.refine == REFINE
    stored = np.asarray(open_map(tmp_path / "map").descriptors)
    queries = stored[:40] + 0.3 * rng.standard_normal((40, 16)).astype(np.float32)
    width = 300 // REFINE
    found = neighbors.search(queries, np.zeros(40, np.int64), width)
    for i, query in enumerate(queries):
        exact = np.linalg.norm(stored - query, axis=1)
        expected = np.lexsort((np.arange(len(stored)), exact))[:width]
        np.testing.assert_array_equal(found.indices[i], expected)
        np.testing.assert_allclose(found.distances[i], exact[expected], rtol=1e-6)
    coded, _ = search_frames(neighbors.index, queries, width)
    assert (coded != found.indices).any()
