"""One record per method and one ``build_matcher``: every family against the matchers it puts together, the
method/model rules, and one set of method names for the CLI, the benchmark, the localiser and the registry."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from seqvpr.cli.match import match
from seqvpr.data.ground_truth import Radius, ground_truth_within_radius
from seqvpr.experiments.benchmark import read_config
from seqvpr.matchers.hierarchical import HierarchicalMatcher
from seqvpr.matchers.retrieval import RetrievalMatcher
from seqvpr.matchers.rows import transform_traversal
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.methods import (
    IMAGE_MODELS, IMPLIED_METHODS, METHODS, MODEL_TITLES, build_matcher, check_models, implied_method, matcher_class,
    models_used, run_length,
)
from seqvpr.models.configs import TransformConfig
from seqvpr.models.registry import TrainedModel
from seqvpr.models.seqmatchnet import FrameTransform
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.descriptors import SeqNet
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.synthetic.routes import generate_route
from tests.helpers import match_method, raises_one_line

SETTINGS = MatchSettings(SequenceSpec(5), k=10)


@pytest.fixture(scope="module")
def pair():
    return generate_route(n_frames=120, dim=16, seed=4)


def trained(kind: str, module, length: int = 5) -> TrainedModel:
    return TrainedModel(kind, module.eval(), length, Path(kind))


SMN = trained("seqmatchnet", FrameTransform(TransformConfig(16), seed=1))
SEQNET = trained("seqnet", SeqNet(16, 16, 3))


def same(a, b) -> None:
    np.testing.assert_array_equal(a.topk.indices, b.topk.indices)
    np.testing.assert_allclose(a.topk.distances, b.topk.distances, rtol=1e-6)


def test_method_names_are_one_set_for_cli_benchmark_and_registry(tmp_path):
    choices = next(p for p in match.params if p.name == "method").type.choices
    assert set(choices) == set(METHODS)
    for name in METHODS:  # the benchmark accepts every method of the registry ...
        config = tmp_path / f"{name}.toml"
        config.write_text(f'[benchmark]\nmethods = ["{name}"]\n[[dataset]]\nname = "d"\nreference = "r.npz"\n'
                          'query = "q.npz"\nradius = "1f"\ntrain = "0:1"\nselect = "1:2"\ntest = "2:3"\n')
        assert read_config(config).methods == (name,)
    config.write_text(config.read_text().replace(f'["{name}"]', '["magic"]'))
    raises_one_line("unknown methods magic", read_config, config)  # ... and nothing else


def test_every_record_builds_the_class_it_names():
    models = {"seqmatchnet": SMN, "seqnet": SEQNET}
    for name, method in METHODS.items():
        if method.needs == "jist":
            continue
        used = {kind: model for kind, model in models.items() if method.accepts(kind) or kind == method.needs}
        assert isinstance(build_matcher(name, SETTINGS, used), matcher_class(method)), name


def test_matching_family(pair):
    reference, query = pair
    same(match_method("matching", reference, query, SETTINGS), SequenceMatcher(SETTINGS).topk(reference, query))
    single = match_method("single", reference, query, SETTINGS)
    assert single.settings.sequence.length == 1
    same(single, SequenceMatcher(replace(SETTINGS, sequence=SequenceSpec(1))).topk(reference, query))
    transformed = (transform_traversal(reference, SMN.module), transform_traversal(query, SMN.module))
    expected = SequenceMatcher(SETTINGS).topk(*transformed)
    same(match_method("seqmatchnet", reference, query, SETTINGS, {"seqmatchnet": SMN}), expected)
    same(match_method("matching", reference, query, SETTINGS, {"seqmatchnet": SMN}), expected)


@pytest.mark.parametrize("name", ["single", "hmm", "graph"])
def test_one_frame_methods_score_one_frame_a_query_whatever_length_is_asked(pair, name):
    from seqvpr.evaluation.scoring import evaluate_match

    reference, query = pair
    result = match_method(name, reference, query, replace(SETTINGS, sequence=SequenceSpec(9)))
    assert result.settings.sequence.length == 1  # the benchmark asks every method for its table's L
    gt = ground_truth_within_radius(query, reference, Radius(4, "m"))
    evaluation = evaluate_match(result, gt, (1,))
    top = result.topk.indices[:, 0]
    assert evaluation.frame_precision == pytest.approx(gt.contains(np.arange(len(query)), top).mean())


def test_retrieval_and_hierarchical_families(pair):
    reference, query = pair
    same(match_method("delta", reference, query, SETTINGS), RetrievalMatcher(SETTINGS, "delta").topk(reference, query))
    same(match_method("seqnet", reference, query, SETTINGS, {"seqnet": SEQNET}),
         RetrievalMatcher(SETTINGS, "seqnet", SEQNET.module).topk(reference, query))
    # HVPR: the SeqNet shortlist over the frames as described, re-ranked over SeqMatchNet-transformed frames
    shortlist = RetrievalMatcher(replace(SETTINGS, k=20), "seqnet", SEQNET.module).topk(reference, query)
    transformed = (transform_traversal(reference, SMN.module), transform_traversal(query, SMN.module))
    hvpr = match_method("hvpr", reference, query, SETTINGS, {"seqnet": SEQNET, "seqmatchnet": SMN})
    same(hvpr, SequenceMatcher(SETTINGS).rerank(*transformed, shortlist.topk))
    composed = HierarchicalMatcher(RetrievalMatcher(SETTINGS, "seqnet", SEQNET.module),
                                   SequenceMatcher(SETTINGS, transform=SMN.module))
    same(hvpr, composed.topk(reference, query))
    seqgem = match_method("hvpr", reference, query, SETTINGS, proposer="seqgem")
    same(seqgem, match_method("seqgem", reference, query, SETTINGS, rerank=20))
    gt = ground_truth_within_radius(query, reference, Radius(4, "m"))
    assert gt.contains(np.arange(len(query)), hvpr.topk.indices[:, 0]).any()


def test_models_and_methods_that_do_not_go_together_are_one_line_errors():
    jist = {"jist": trained("jist", SeqNet(4, 4, 1))}
    raises_one_line("method seqnet needs a SeqNet model (models; seqvpr train seqnet --out), got none", check_models,
                    METHODS["seqnet"], {})
    raises_one_line("got a SeqMatchNet model", check_models, METHODS["jist"], {"seqmatchnet": SMN})
    raises_one_line("use method seqnet", check_models, METHODS["delta"], {"seqnet": SEQNET})
    raises_one_line("a JIST model and a CosPlace model (models) both describe the images", check_models,
                    METHODS["matching"], {**jist, "cosplace": trained("cosplace", SeqNet(4, 4, 1), length=1)})
    check_models(METHODS["matching"], jist)  # JIST's frame encoder describes the frames any method matches
    raises_one_line("rerank N needs", match_method, "matching", None, None, SETTINGS, rerank=5)
    raises_one_line("method 'magic' is not known", match_method, "magic", None, None, SETTINGS)


def test_model_tables_agree_with_the_registry():
    from seqvpr.models.registry import MODEL_KINDS

    assert MODEL_TITLES == {name: kind.title for name, kind in MODEL_KINDS.items()}
    assert IMPLIED_METHODS == {name: kind.method for name, kind in MODEL_KINDS.items()}
    assert set(IMPLIED_METHODS.values()) <= set(METHODS)
    assert set(IMAGE_MODELS) == {name for name, kind in MODEL_KINDS.items() if kind.consumes == "images"}


def test_a_cosplace_model_describes_frames_for_any_method_but_jist():
    cosplace = {"cosplace": trained("cosplace", SeqNet(4, 4, 1), length=1)}
    assert implied_method(cosplace) == "single"
    assert implied_method({**cosplace, "seqmatchnet": SMN}) == "seqmatchnet"
    assert implied_method({**cosplace, "seqnet": SEQNET}) == "seqnet"
    for name in ("single", "matching", "seqgem", "delta", "hvpr", "seqmatchnet", "seqnet"):
        check_models(METHODS[name], {**cosplace, **{k: m for k, m in (("seqmatchnet", SMN), ("seqnet", SEQNET))
                                                    if METHODS[name].needs == k}})
    raises_one_line("needs a JIST model (models;", check_models, METHODS["jist"], cosplace)
    jist = {"jist": trained("jist", SeqNet(4, 4, 1))}
    raises_one_line("a JIST model and a CosPlace model (models) both describe the images", check_models, METHODS["jist"],
                    {**jist, **cosplace})
    assert run_length(METHODS["matching"], {**cosplace, "seqmatchnet": trained("seqmatchnet", SMN.module, 3)}) == 3
    assert run_length(METHODS["seqgem"], cosplace) == 1 and run_length(METHODS["single"], cosplace) == 1


def test_implied_method_length_and_models_used():
    assert implied_method({}) == "matching" and implied_method({"seqmatchnet": SMN}) == "seqmatchnet"
    assert implied_method({"seqmatchnet": SMN, "seqnet": SEQNET}) == "seqnet"
    assert run_length(METHODS["seqnet"], {"seqmatchnet": trained("seqmatchnet", SMN.module, 3), "seqnet": SEQNET}) == 5
    assert run_length(METHODS["matching"], {}) == 1
    assert models_used("hvpr") == ("seqmatchnet", "seqnet") and models_used("hvpr", "seqgem") == ("seqmatchnet",)
    assert models_used("jist") == ("jist",) and models_used("delta") == ()


def test_a_new_method_is_one_record_plus_its_function(monkeypatch, pair):
    """The documented how-to (docs/concepts/architecture.md): a pooling function and one Method record make a
    method ``seqvpr.match`` runs."""
    import torch

    from seqvpr.methods import Method
    from seqvpr.sequences import descriptors

    def maxpool(windows: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.normalize(windows.amax(dim=1), dim=-1)

    monkeypatch.setitem(descriptors.FIXED_POOLINGS, "maxpool", maxpool)
    monkeypatch.setitem(METHODS, "maxpool", Method("maxpool", "retrieval", "element-wise max", pooling="maxpool"))
    reference, query = pair
    result = match_method("maxpool", reference, query, SETTINGS)
    ref, qry = (torch.nn.functional.normalize(torch.as_tensor(t.descriptors, dtype=torch.float32), dim=1)
                for t in pair)
    window = lambda x, i: maxpool(x[i - 2 : i + 3][None])[0]  # noqa: E731 (centred L = 5)
    i = 60
    expected = min(range(2, len(ref) - 2), key=lambda j: float(torch.dist(window(qry, i), window(ref, j))))
    assert result.topk.indices[i, 0] == expected
