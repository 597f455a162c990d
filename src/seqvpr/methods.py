"""One record per method, which every entry point uses (``seqvpr.match``, ``seqvpr match``, ``seqvpr benchmark``,
the demo, the localiser) through ``build_matcher``: the record names its matcher class and defaults.

A method is frame-level sequence matching (``single``, ``matching``, ``seqmatchnet``), retrieval by one sequence
descriptor per window (``smoothing``, ``delta``, ``concat``, ``seqgem``, ``seqgem-signed``, ``seqnet``, ``jist``),
hierarchical (``hvpr``: a retrieval shortlist re-ranked by exact sequence distance), or a filter (``hmm``: a
topological HMM over reference frames, run forward over the query). Trained models come in as
``TrainedModel``s keyed by kind: a SeqMatchNet model transforms the frames that sequence matching compares (the
matching methods and every re-ranking); SeqNet and JIST give their own sequence descriptors; a CosPlace model is a
frame encoder only. Sequence-descriptor methods pool the frames as described: the model that consumes images (JIST's
encoder, or CosPlace, at most one of them) describes them, ``describe_for_models``.

Adding a method: one ``Method`` record in ``METHODS`` and, when no family fits, a matcher class it names
(``seqvpr.matchers``; a ``WindowMatcher`` writes one window distance); the CLI's ``--method`` choices and the
benchmark's accepted methods are ``METHODS``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SettingError
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.threads import ensure_policy

if TYPE_CHECKING:
    from seqvpr.matchers.base import Matcher
    from seqvpr.sequences.match_settings import MatchSettings
    from seqvpr.models.registry import TrainedModel
    from seqvpr.progress import ProgressFactory

Family = Literal["matching", "retrieval", "hierarchical", "filter", "graph"]
#: the matcher class of each family (``module:Class``), unless a record names its own
FAMILY_MATCHERS = {
    "matching": "seqvpr.matchers.sequence:SequenceMatcher",
    "retrieval": "seqvpr.matchers.retrieval:RetrievalMatcher",
    "hierarchical": "seqvpr.matchers.hierarchical:HierarchicalMatcher",
    "filter": "seqvpr.matchers.filter:FilterMatcher",
    "graph": "seqvpr.matchers.graph:GraphMatcher",
}
MODEL_TITLES = {"seqmatchnet": "SeqMatchNet", "seqnet": "SeqNet", "jist": "JIST", "cosplace": "CosPlace"}
#: the method each model kind implies, the first kind given in this order deciding (the registry's ``method``)
IMPLIED_METHODS = {"jist": "jist", "seqnet": "seqnet", "seqmatchnet": "seqmatchnet", "cosplace": "single"}
#: the kinds that describe the images themselves (the registry's ``consumes="images"``); one per run at most
IMAGE_MODELS = ("jist", "cosplace")


@dataclass(frozen=True)
class Method:
    """A method: its family (and so its matcher class, unless ``matcher`` names another as ``module:Class``), the
    model kind it needs (if any), the sequence-descriptor pooling it retrieves with, a fixed sequence length
    (``single``: 1), its window search (``seqvpr.matchers.sequence.SequenceSearch``), the score threshold a
    localiser uses before one is calibrated, and a line saying what it is."""

    name: str
    family: Family
    summary: str
    needs: str | None = None
    pooling: str | None = None
    length: int | None = None
    search: str = "velocity"  # how a window is scored: the kernel's constant velocity, adaptive, SeqSLAM's
    threshold: float = 0.1  # the localiser's default score threshold (``seqvpr localize --calibrate`` sets one)
    matcher: str | None = None

    @property
    def matcher_path(self) -> str:
        """``module:Class`` of the matcher that runs this method."""
        return self.matcher or FAMILY_MATCHERS[self.family]

    def accepts(self, kind: str) -> bool:
        """Whether a model of ``kind`` can be given to this method: its own, a model that describes the frames
        (JIST's frame encoder, CosPlace's: any method matches the frames they give), a SeqMatchNet transform for the
        frames it matches or re-ranks, a SeqNet shortlist for ``hvpr``. The ``jist`` method pools its own
        encoder's frames, so no other model goes with it."""
        if kind == self.needs:
            return True
        if self.needs == "jist":
            return False
        return kind in IMAGE_MODELS or kind == "seqmatchnet" or (self.family == "hierarchical" and kind == "seqnet")


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("single", "matching", "single-image retrieval (sequence matching at L = 1)", length=1),
    Method("matching", "matching", "sequence matching: mean of order-aligned frame distances over L frames"),
    Method("seqmatchnet", "matching", "sequence matching over SeqMatchNet-transformed frames", needs="seqmatchnet"),
    Method("adaptive", "matching", "adaptive sequence matching: each query frame moves the reference by --steps "
           "MIN:MAX frames (stops, speed changes; DTW-like)", search="adaptive"),
    Method("seqslam", "matching", "SeqSLAM: local contrast enhancement of the distance matrix (10 reference frames), "
           "then sequence matching (OpenSeqSLAM2's trajectory search: --velocities 0.8:1.2:0.1)", search="seqslam"),
    Method("seqslam-cone", "matching", "OpenSeqSLAM2's cone search: the share of the window's frames whose single-image "
           "best match lies between the slowest and fastest --velocities trajectories (votes, no distances)",
           search="seqslam-cone"),
    Method("seqslam-hybrid", "matching", "OpenSeqSLAM2's hybrid search: contrast enhancement, then the best of the "
           "--velocities trajectories that pass through some frame's single-image best match", search="seqslam-hybrid"),
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
           "by adaptive matching inside each candidate stretch (--steps)", search="adaptive"),
    Method("hmm", "filter", "topological filter (HMM forward pass) over reference frames: stops and speed changes",
           length=1, threshold=0.5),
    Method("graph", "graph", "GISM-style graph matching: the cheapest whole path through the distance matrix, "
           "moving 0..--steps MAX reference frames a query frame, with a hidden node for jumps (offline)", length=1),
)}


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise SettingError(f"{{method}} {name!r} is not known (choose from: {', '.join(METHODS)})")
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
        titles = " and a ".join(f"{MODEL_TITLES[kind]} model" for kind in describing)
        raise SettingError(f"a {titles} ({{models}}) both describe the images: give one of them")
    if method.needs is not None and method.needs not in models:
        given = next(iter(models), None)
        found = "none" if given is None else f"a {MODEL_TITLES[given]} model"
        raise SettingError(f"{{method}} {method.name} needs a {MODEL_TITLES[method.needs]} model ({{models}}; "
                           f"seqvpr train {method.needs} --out), got {found}")
    for kind in models:
        if not method.accepts(kind):
            advice = (f"gives sequence descriptors itself: use {{method}} {kind} (or leave {{method}} out)"
                      if kind in ("seqnet", "jist") else "does not apply")
            raise SettingError(f"a {MODEL_TITLES[kind]} model ({{models}}) {advice}, not {{method}} {method.name}")


def check_run(name: str, models: Mapping[str, TrainedModel], rerank: int = 0, length: int | None = None) -> Method:
    """The method, after checking that it goes with these models, this re-ranking and this sequence length (before
    any data is read)."""
    method = get_method(name)
    check_models(method, models)
    if rerank < 0 or (rerank and method.family == "matching"):
        raise SettingError(f"{{rerank}} N needs N >= 0 and a {{method}} other than matching (got {rerank}, {name})")
    if method.length is not None and length not in (None, method.length):
        raise SettingError(f"{{method}} {name} uses L = {method.length}; leave {{seq_len}} out (got {length})")
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
    """The model kinds method ``name`` uses (what the benchmark trains for it)."""
    method = get_method(name)
    if method.family == "hierarchical":
        return ("seqmatchnet", *models_used(shortlist))
    return () if method.needs is None else (method.needs,)


def matcher_class(method: Method) -> type[Matcher]:
    """The class a method's record names (imported when first asked: ``import seqvpr`` stays light)."""
    module, _, name = method.matcher_path.partition(":")
    return getattr(importlib.import_module(module), name)


def build_matcher(
    name: str,
    settings: MatchSettings,
    models: Mapping[str, TrainedModel] | None = None,
    *,
    progress: ProgressFactory | None = None,
    **conf: Any,
) -> Matcher:
    """The matcher of method ``name`` under ``settings`` with these models, its family's own settings from ``conf``
    (``steps``, ``contrast_window``, ``index``, ``rerank`` N, ``proposer``: hvpr's retrieval method, ``filter``,
    ``seed``). A method
    of fixed length (``single``, ``hmm``, ``graph``) matches one frame a query, whatever length was asked."""
    ensure_policy()  # the one thread policy (seqvpr.threads)
    models = dict(models or {})
    if conf.pop("accepted_only", False):  # a part of another method's matcher: the models this one takes
        models = {kind: model for kind, model in models.items() if get_method(name).accepts(kind)}
    method = check_run(name, models, conf.get("rerank") or 0)
    if method.length is not None:
        settings = replace(settings, sequence=SequenceSpec(method.length))
    built = matcher_class(method).from_method(method, settings, models, build_matcher, progress=progress, **conf)
    built.method = method.name
    return built


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
    engine: str = "auto",
) -> tuple[Traversal, Traversal]:
    """Frame descriptors of both traversals: the model that consumes images (JIST's encoder, CosPlace) reads them
    at its image size, or at ``image_size`` (width, height) when given, run by ``engine``; without one,
    ``describe_pair`` (e.g. patch normalisation or a backbone, as the caller chose)."""
    model = image_model(models)
    if model is None:
        return describe_pair(reference, query)
    from seqvpr.models.jist import ImageStore, describe_images

    width, height = image_size or model.image_size
    store = ImageStore(width, height)
    return tuple(describe_images(model.module, t, width, height, device, store=store,  # type: ignore[return-value]
                                 engine=engine) for t in (reference, query))
