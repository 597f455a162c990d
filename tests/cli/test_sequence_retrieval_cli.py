"""`seqvpr match --method` (sequence descriptors + faiss) and `--rerank` (HVPR) through the command line."""

import json

import pytest

from seqvpr.synthetic.routes import write_demo_route
from tests.helpers import run_cli


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    return write_demo_route(tmp_path_factory.mktemp("route"), n_frames=240, seed=5)


def match(monkeypatch, capsys, tmp_path, route, *args):
    ref, qry = route
    code, stdout, stderr = run_cli(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "10m", "--json",
                                   "--k", "1,5,20", "--out", tmp_path / "o", *args)
    assert code == 0, stderr
    return json.loads(stdout)


def test_smoothing_at_length_one_is_single_image_retrieval(monkeypatch, capsys, tmp_path, route):
    single = match(monkeypatch, capsys, tmp_path, route, "-L", "1")
    smooth = match(monkeypatch, capsys, tmp_path, route, "-L", "1", "--method", "smoothing")
    assert smooth["recall"] == pytest.approx(single["recall"])
    assert smooth["settings"]["method"] == "smoothing" and smooth["settings"]["index"] == "flat"


def test_rerank_of_the_whole_reference_equals_sequence_matching(monkeypatch, capsys, tmp_path, route):
    exhaustive = match(monkeypatch, capsys, tmp_path, route, "-L", "5")
    hvpr = match(monkeypatch, capsys, tmp_path, route, "-L", "5", "--method", "seqgem", "--rerank", "240")
    shortlist = match(monkeypatch, capsys, tmp_path, route, "-L", "5", "--method", "seqgem")
    assert hvpr["recall"] == pytest.approx(exhaustive["recall"])
    assert hvpr["settings"]["rerank"] == 240
    assert shortlist["recall"] != pytest.approx(exhaustive["recall"])  # the shortlist alone ranks differently


@pytest.mark.parametrize("method", ["delta", "concat", "seqgem-signed"])
def test_every_descriptor_method_scores_every_query_with_a_window(monkeypatch, capsys, tmp_path, route, method):
    exhaustive = match(monkeypatch, capsys, tmp_path, route, "-L", "5")
    result = match(monkeypatch, capsys, tmp_path, route, "-L", "5", "--method", method, "--index", "hnsw")
    assert result["queries_evaluated"] == exhaustive["queries_evaluated"]
    assert 0.0 < result["recall"]["20"] <= 1.0


def test_rerank_needs_a_descriptor_method(monkeypatch, capsys, tmp_path, route):
    ref, qry = route
    code, _, stderr = run_cli(monkeypatch, capsys, "match", "-r", ref, "-q", qry, "--radius", "10m", "--rerank", "5",
                              "--out", tmp_path / "bad")
    assert code == 2 and "--rerank N needs" in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "bad").exists()
