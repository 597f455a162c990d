"""One record per method and one ``run_method`` that every entry point uses (``seqvpr match``, ``seqvpr
benchmark``, the demo).

A method is frame-level sequence matching (``single``, ``matching``, ``seqmatchnet``), retrieval by one sequence
descriptor per window (``smoothing``, ``delta``, ``concat``, ``seqgem``, ``seqgem-signed``, ``seqnet``, ``jist``),
hierarchical (``hvpr``: a retrieval shortlist re-ranked by exact sequence distance), or a filter (``hmm``: a
topological HMM over reference frames, run forward over the query). Trained models come in as
``TrainedModel``s keyed by kind: a SeqMatchNet model transforms the frames that sequence matching compares (the
matching methods and every re-ranking); SeqNet and JIST give their own sequence descriptors; a CosPlace model is a
frame encoder only. Sequence-descriptor methods pool the frames as described: the model that consumes images (JIST's
encoder, or CosPlace, at most one of them) describes them, ``describe_for_models``.

Adding a method: one ``Method`` record in ``METHODS`` and, when no family fits, a branch of ``run_method``; the
CLI's ``--method`` choices and the benchmark's accepted methods are ``METHODS``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.threads import ensure_policy

if TYPE_CHECKING:
    from seqvpr.models.registry import TrainedModel
    from seqvpr.pipeline import MatchResult, MatchSettings, ProgressFactory

Family = Literal["matching", "retrieval", "hierarchical", "filter"]
MODEL_TITLES = {"seqmatchnet": "SeqMatchNet", "seqnet": "SeqNet", "jist": "JIST", "cosplace": "CosPlace"}
#: the method each model kind implies, the first kind given in this order deciding (the registry's ``method``)
IMPLIED_METHODS = {"jist": "jist", "seqnet": "seqnet", "seqmatchnet": "seqmatchnet", "cosplace": "single"}
#: the kinds that describe the images themselves (the registry's ``consumes="images"``); one per run at most
IMAGE_MODELS = ("jist", "cosplace")
HVPR_SHORTLIST = 20  # HVPR's default shortlist length (the top N re-ranked)


@dataclass(frozen=True)
class Method:
    """A method: its family, the model kind it needs (if any), the sequence-descriptor pooling it retrieves with,
    a fixed sequence length (``single``: 1), and a line saying what it is."""

    name: str
    family: Family
    summary: str
    needs: str | None = None
    pooling: str | None = None
    length: int | None = None
    scorer: str | None = None  # a matching method's window distance other than the kernel's constant velocity

    def accepts(self, kind: str) -> bool:
        """Whether a model of ``kind`` can be given to this method: its own, a CosPlace encoder describing the
        frames, a SeqMatchNet transform for the frames it matches or re-ranks, a SeqNet shortlist for ``hvpr``.
        JIST's frames are its own encoder's, so nothing else goes with it."""
        if kind == self.needs:
            return True
        if self.needs == "jist" or kind == "jist":
            return False
        return kind in ("cosplace", "seqmatchnet") or (self.family == "hierarchical" and kind == "seqnet")


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("single", "matching", "single-image retrieval (sequence matching at L = 1)", length=1),
    Method("matching", "matching", "sequence matching: mean of order-aligned frame distances over L frames"),
    Method("seqmatchnet", "matching", "sequence matching over SeqMatchNet-transformed frames", needs="seqmatchnet"),
    Method("adaptive", "matching", "adaptive sequence matching: each query frame moves the reference by --steps "
           "MIN:MAX frames (stops, speed changes; DTW-like)", scorer="adaptive"),
    Method("seqslam", "matching", "SeqSLAM: local contrast enhancement of the distance matrix (10 reference frames), "
           "then sequence matching (OpenSeqSLAM2's trajectory search: --velocities 0.8:1.2:0.1)", scorer="seqslam"),
    Method("seqslam-cone", "matching", "OpenSeqSLAM2's cone search: the share of the window's frames whose single-image "
           "best match lies between the slowest and fastest --velocities trajectories (votes, no distances)",
           scorer="seqslam-cone"),
    Method("seqslam-hybrid", "matching", "OpenSeqSLAM2's hybrid search: contrast enhancement, then the best of the "
           "--velocities trajectories that pass through some frame's single-image best match", scorer="seqslam-hybrid"),
    Method("smoothing", "retrieval", "window mean of the frames (smoothing), faiss search", pooling="smoothing"),
    Method("delta", "retrieval", "Delta descriptors, faiss search", pooling="delta"),
    Method("concat", "retrieval", "the concatenated window, faiss search", pooling="concat"),
    Method("seqgem", "retrieval", "SeqGeM (p = 3) of the window, faiss search", pooling="seqgem"),
    Method("seqgem-signed", "retrieval", "SeqGeM keeping negative parts (for PCA-whitened or HDC descriptors)",
           pooling="seqgem-signed"),
    Method("seqnet", "retrieval", "a trained SeqNet's sequence descriptor, faiss search", needs="seqnet",
           pooling="seqnet"),
    Method("jist", "retrieval", "a trained JIST: its encoder's frames pooled by its SeqGeM, faiss search",
           needs="jist", pooling="seqgem"),
    Method("hvpr", "hierarchical", "hierarchical: a SeqNet (or SeqGeM) shortlist re-ranked by sequence matching"),
    Method("casevpr", "hierarchical", "CaseVPR's hierarchy: a SeqNet (or SeqGeM) shortlist of start points re-ranked "
           "by adaptive matching inside each candidate stretch (--steps)", scorer="adaptive"),
    Method("hmm", "filter", "topological filter (HMM forward pass) over reference frames: stops and speed changes",
           length=1),
    Method("graph", "filter", "GISM-style graph matching: the cheapest whole path through the distance matrix, "
           "moving 0..--steps MAX reference frames a query frame, with a hidden node for jumps (offline)", length=1,
           scorer="graph"),
)}


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise SeqvprError(f"method {name!r} is not known (choose from: {', '.join(METHODS)})")
    return METHODS[name]


def implied_method(models: Mapping[str, TrainedModel]) -> str:
    """The method a set of models implies: JIST's or SeqNet's own, SeqMatchNet's, single-image retrieval for a
    CosPlace encoder alone, or plain sequence matching."""
    for kind, method in IMPLIED_METHODS.items():
        if kind in models:
            return method
    return "matching"


def check_models(method: Method, models: Mapping[str, TrainedModel]) -> None:
    """A method and models that do not go together are a one-line error."""
    describing = [kind for kind in IMAGE_MODELS if kind in models]
    if len(describing) > 1:
        titles = " and a ".join(f"{MODEL_TITLES[kind]} --model" for kind in describing)
        raise SeqvprError(f"a {titles} both describe the images: give one of them")
    if method.needs is not None and method.needs not in models:
        given = next(iter(models), None)
        found = "no --model" if given is None else f"a {MODEL_TITLES[given]} --model"
        raise SeqvprError(f"--method {method.name} needs a {MODEL_TITLES[method.needs]} --model "
                          f"(seqvpr train {method.needs} --out), got {found}")
    for kind in models:
        if not method.accepts(kind):
            advice = (f"gives sequence descriptors itself: use --method {kind} (or leave --method out)"
                      if kind in ("seqnet", "jist") else "does not apply")
            raise SeqvprError(f"a {MODEL_TITLES[kind]} --model {advice}, not --method {method.name}")


def check_run(name: str, models: Mapping[str, TrainedModel], rerank: int = 0, length: int | None = None) -> Method:
    """The method, after checking that it goes with these models, this re-ranking and this sequence length (before
    any data is read)."""
    method = get_method(name)
    check_models(method, models)
    if rerank < 0 or (rerank and method.family == "matching"):
        raise SeqvprError(f"--rerank N needs N >= 0 and a --method other than matching (got {rerank}, {name})")
    if method.length is not None and length not in (None, method.length):
        raise SeqvprError(f"--method {name} uses L = {method.length}; leave --seq-len out (got {length})")
    return method


def run_length(method: Method, models: Mapping[str, TrainedModel]) -> int:
    """The sequence length a method runs at when none is asked for: its own fixed one, its model's (the one it
    needs, else the first given that does not describe images), else 1."""
    if method.length is not None:
        return method.length
    if method.needs in models:
        return models[method.needs].length
    return next((model.length for kind, model in models.items() if kind not in IMAGE_MODELS), 1)


def models_used(name: str, shortlist: str = "seqnet") -> tuple[str, ...]:
    """The model kinds ``run_method(name, ...)`` uses (what the benchmark trains for it)."""
    method = get_method(name)
    if method.family == "hierarchical":
        return ("seqmatchnet", *models_used(shortlist))
    return () if method.needs is None else (method.needs,)


def run_method(
    name: str,
    reference: Traversal,
    query: Traversal,
    settings: MatchSettings,
    models: Mapping[str, TrainedModel] | None = None,
    *,
    index: str = "flat",
    rerank: int = 0,
    shortlist: str | None = None,
    progress: ProgressFactory | None = None,
    rerank_scorer=None,
) -> MatchResult:
    """Top-K reference frames per query frame by method ``name`` over described traversals.

    ``rerank`` N > 0 re-ranks the top N of a retrieval method by exact sequence distance (HVPR; ``hvpr`` itself
    defaults to N = 20 and to the ``shortlist`` method ``seqnet`` when a SeqNet model is given, else ``seqgem``).
    """
    ensure_policy()  # the one thread policy (seqvpr.threads)
    from seqvpr.pipeline import match_traversals, rerank_match, retrieve_traversals

    models = dict(models or {})
    method = check_run(name, models, rerank)
    if method.length is not None:  # single, hmm, graph: one frame a query, whatever length was asked
        settings = replace(settings, sequence=SequenceSpec(method.length))
    if method.family == "hierarchical":
        first = shortlist or ("seqnet" if "seqnet" in models else "seqgem")
        if get_method(first).family != "retrieval":
            raise SeqvprError(f"hvpr: the shortlist must be a retrieval method, got {first!r}")
        used = {kind: models[kind] for kind in models if get_method(first).accepts(kind)}
        return run_method(first, reference, query, settings, used, index=index, rerank=rerank or HVPR_SHORTLIST,
                          rerank_scorer=window_scorer(method, settings))
    if method.family == "filter" and method.scorer == "graph":
        from seqvpr.pipeline import graph_traversals

        return graph_traversals(*transformed_frames(reference, query, models, settings.device), settings)
    if method.family == "filter":
        from seqvpr.pipeline import filter_traversals

        return filter_traversals(*transformed_frames(reference, query, models, settings.device), settings)
    if method.family == "matching":
        return match_traversals(*transformed_frames(reference, query, models, settings.device), settings, progress,
                                scorer=window_scorer(method, settings))
    shortlist_settings = replace(settings, k=max(rerank, settings.k))
    result = retrieve_traversals(reference, query, method.pooling, shortlist_settings, index=index,
                                 model=_pooling_module(method, models))
    if not rerank:
        return result
    ref, qry = transformed_frames(reference, query, models, settings.device)
    return rerank_match(replace(result, reference=ref, query=qry), settings, scorer=rerank_scorer)


def window_scorer(method: Method, settings: MatchSettings):
    """The window distance a matching method uses: None for the kernel's constant velocity, else its scorer."""
    if method.scorer == "adaptive":
        from seqvpr.sequences.adaptive import AdaptiveScorer

        return AdaptiveScorer(*settings.steps)
    if method.scorer in ("seqslam", "seqslam-cone", "seqslam-hybrid"):
        from seqvpr.sequences.seqslam import ConeScorer, ContrastScorer, HybridScorer

        if method.scorer == "seqslam-cone":  # it counts votes: the enhanced distances would go unread
            return ConeScorer()
        return ContrastScorer(settings.contrast_window, HybridScorer() if method.scorer == "seqslam-hybrid" else None)
    return None


def _pooling_module(method: Method, models: Mapping[str, TrainedModel]):
    """The learned pooling a retrieval method uses: SeqNet itself, JIST's SeqGeM, or none."""
    if method.needs == "seqnet":
        return models["seqnet"].module
    if method.needs == "jist":
        return models["jist"].module.sequence_pool
    return None


def transformed_frames(
    reference: Traversal, query: Traversal, models: Mapping[str, TrainedModel], device: str = "cpu"
) -> tuple[Traversal, Traversal]:
    """Both traversals through a SeqMatchNet model's per-frame transform when one is given; else unchanged."""
    if "seqmatchnet" not in models:
        return reference, query
    from seqvpr.pipeline import transform_traversal

    module = models["seqmatchnet"].module
    return transform_traversal(reference, module, device), transform_traversal(query, module, device)


def image_model(models: Mapping[str, TrainedModel]) -> TrainedModel | None:
    """The model that describes the images itself (JIST's encoder, CosPlace), if one is given."""
    return next((models[kind] for kind in IMAGE_MODELS if kind in models), None)


def describe_for_models(
    reference: Traversal,
    query: Traversal,
    models: Mapping[str, TrainedModel],
    describe_pair: Callable[[Traversal, Traversal], tuple[Traversal, Traversal]],
    device: str = "cpu",
    image_size: tuple[int, int] | None = None,
) -> tuple[Traversal, Traversal]:
    """Frame descriptors of both traversals: the model that consumes images (JIST's encoder, CosPlace) reads them
    at its image size, or at ``image_size`` (width, height) when given; without one, ``describe_pair`` (e.g. patch
    normalisation or a backbone, as the caller chose)."""
    model = image_model(models)
    if model is None:
        return describe_pair(reference, query)
    from seqvpr.models.jist import ImageStore, describe_images

    width, height = image_size or model.image_size
    store = ImageStore(width, height)
    return tuple(describe_images(model.module, t, width, height, device, store=store)  # type: ignore[return-value]
                 for t in (reference, query))
