"""Matching against a saved map gives what matching its sources directly gives, for every method; mismatched
queries and models are one-line errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from seqvpr.data.sources import load_traversal
from seqvpr.maps import FrameDescription, build_map, open_map, match_map
from seqvpr.methods import METHODS, describe_for_models
from tests.helpers import match_method
from seqvpr.models.configs import JistConfig, TransformConfig
from seqvpr.models.jist import build_jist, save_jist
from seqvpr.models.registry import load_trained_model
from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet
from seqvpr.models.seqnet import save_seqnet
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.descriptors import SeqNet
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.synthetic.world import write_demo_world
from tests.helpers import raises_one_line, write_route_files

SETTINGS = MatchSettings(SequenceSpec(5), k=10)
#: the models each method is run with (hvpr: SeqNet shortlist, SeqMatchNet re-ranking)
METHOD_MODELS = {"seqmatchnet": ("seqmatchnet",), "seqnet": ("seqnet",), "hvpr": ("seqnet", "seqmatchnet")}


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    folder = write_route_files(tmp_path_factory.mktemp("route"), 120, 16, 4)
    save_seqmatchnet(folder / "smn", FrameTransform(TransformConfig(16), seed=1), {"sequence": {"length": 5}})
    save_seqnet(folder / "seqnet", SeqNet(16, 16, 3), {"sequence": {"length": 5}})
    return folder


def models_of(folder, kinds):
    names = {"seqmatchnet": "smn", "seqnet": "seqnet"}
    return {kind: load_trained_model(folder / names[kind]) for kind in kinds}


def same(a, b) -> None:
    np.testing.assert_array_equal(a.topk.indices, b.topk.indices)
    np.testing.assert_allclose(a.topk.distances, b.topk.distances, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", [m for m in METHODS if m != "jist"])
def test_every_method_gives_the_direct_result(route, tmp_path, method):
    models = models_of(route, METHOD_MODELS.get(method, ()))
    stored = {k: m for k, m in models.items() if k == "seqmatchnet" and METHODS[method].family == "matching"}
    saved = build_map([str(route / "ref.npz")], tmp_path / "m", models=stored)
    reference, query = load_traversal(route / "ref.npz", "reference"), load_traversal(route / "qry.npz", "query")
    direct = match_method(method, reference, query, SETTINGS, models)
    same(match_map(saved, query, method, SETTINGS, models), direct)


def test_a_memory_budget_that_chunks_the_map_changes_nothing(route, tmp_path):
    saved = build_map([str(route / "ref.npz")], tmp_path / "m")
    query = load_traversal(route / "qry.npz", "query")
    whole = match_map(saved, query, "matching", SETTINGS)
    small = match_map(saved, query, "matching", replace(SETTINGS, memory_budget=2 * 4 * 130 * 40))
    np.testing.assert_array_equal(small.topk.indices, whole.topk.indices)


def test_a_float16_map_ranks_as_the_float32_one(route, tmp_path):
    query = load_traversal(route / "qry.npz", "query")
    wide = match_map(build_map([str(route / "ref.npz")], tmp_path / "a"), query, "matching", SETTINGS)
    half = match_map(build_map([str(route / "ref.npz")], tmp_path / "b", dtype="float16"), query, "matching", SETTINGS)
    assert (half.topk.indices[:, 0] == wide.topk.indices[:, 0]).mean() > 0.95
    np.testing.assert_allclose(half.topk.distances[:, 0], wide.topk.distances[:, 0], atol=2e-3)


def test_jist_frames_are_stored_and_the_query_goes_through_the_same_encoder(tmp_path):
    world = write_demo_world(tmp_path / "world", frames=24, width=64, height=48, seed=0, query_condition="dusk")
    config = JistConfig(backbone="efficientnet-lite0", weights=None, out_dim=16, seq_length=3)
    save_jist(tmp_path / "jist", build_jist(config).eval(), config, {"image_size": [64, 48], "sequence": {"length": 3}})
    models = {"jist": load_trained_model(tmp_path / "jist")}
    saved = build_map([str(world["test_reference"])], tmp_path / "m", FrameDescription(), models)
    assert saved.info.description["descriptor"] == "jist" and saved.info.model["jist"]["sha256"]
    reference = load_traversal(world["test_reference"], "reference")
    query = load_traversal(world["test_query"], "query")
    settings = replace(SETTINGS, sequence=SequenceSpec(3))
    described = describe_for_models(reference, query, models, lambda r, q: (r, q))
    direct = match_method("jist", *described, settings, models)
    same(match_map(saved, query, "jist", settings, models), direct)
    raises_one_line("was built through the jist model", match_map, saved, query, "seqgem", settings, {})


def test_mismatched_queries_and_models_are_one_line_errors(route, tmp_path):
    query = load_traversal(route / "qry.npz", "query")
    plain = build_map([str(route / "ref.npz")], tmp_path / "plain")
    smn = models_of(route, ("seqmatchnet",))
    transformed = build_map([str(route / "ref.npz")], tmp_path / "smn", models=smn)
    raises_one_line("holds SeqMatchNet-transformed frames, which method seqgem does not use", match_map,
                    transformed, query, "seqgem", SETTINGS, smn)
    raises_one_line("was built through the seqmatchnet model", match_map, transformed, query, "matching", SETTINGS)
    save_seqmatchnet(tmp_path / "other", FrameTransform(TransformConfig(16), seed=2), {"sequence": {"length": 5}})
    other = {"seqmatchnet": load_trained_model(tmp_path / "other")}
    raises_one_line("is not the seqmatchnet model", match_map, transformed, query, "matching", SETTINGS, other)
    narrow = replace(query, descriptors=query.descriptors[:, :8])
    raises_one_line("has 8-D descriptors", match_map, plain, narrow, "matching", SETTINGS)
    raises_one_line("holds normalised descriptors", match_map, plain, query, "matching",
                    replace(SETTINGS, normalize=False))


def test_an_sq8_map_ranks_as_the_float32_one_exactly_and_shortlisted(route, tmp_path):
    from seqvpr.maps.index import IndexSpec, add_index

    query = load_traversal(route / "qry.npz", "query")
    wide = match_map(build_map([str(route / "ref.npz")], tmp_path / "a"), query, "matching", SETTINGS)
    coded = build_map([str(route / "ref.npz")], tmp_path / "b", dtype="sq8")
    exact = match_map(coded, query, "matching", replace(SETTINGS, memory_budget=2 * 4 * 130 * 40))
    assert (exact.topk.indices[:, 0] == wide.topk.indices[:, 0]).mean() > 0.95
    add_index(coded, IndexSpec("flat"))
    shortlisted = match_map(open_map(tmp_path / "b"), query, "matching", SETTINGS, shortlist=120)
    np.testing.assert_array_equal(shortlisted.topk.indices[:, 0], exact.topk.indices[:, 0])
    assert (match_map(coded, query, "seqgem", SETTINGS).topk.indices[:, 0] >= 0).any()  # decoded for retrieval
