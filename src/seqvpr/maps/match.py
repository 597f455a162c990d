"""Matching a query against a saved map: the query described as the map's frames were, the models checked against
the ones the map went through, then ``run_method`` as for any reference (frame matching reads the map chunk by
chunk; sequence-descriptor methods pool its frames)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.maps.build import FrameDescription, describe_frames, model_records
from seqvpr.maps.files import MapInfo, SavedMap
from seqvpr.maps.index import model_record
from seqvpr.methods import METHODS, build_matcher, check_run
from seqvpr.models.registry import TrainedModel
from seqvpr.matchers.base import MatchResult, MatchSettings
from seqvpr.matchers.frames import transformed_by
from seqvpr.progress import ProgressFactory
from seqvpr.progress import or_logged
from seqvpr.threads import ensure_policy

if TYPE_CHECKING:
    from seqvpr.sequences.topk import TopK


def check_map_models(info: MapInfo, folder: str, method: str, models: Mapping[str, TrainedModel]) -> None:
    """The models a map's frames went through must be given again (same weights); an image model it was not built
    with cannot describe its frames. A SeqMatchNet model given to a map built without one transforms both sides at
    match time; a map built through one holds transformed frames, which only the frame-matching methods use."""
    built = info.model or {}
    given = model_records(models) or {}
    for kind, record in built.items():
        if kind not in given:
            raise SeqvprError(f"{folder} was built through the {kind} model {record['folder']} "
                              f"(sha256 {record['sha256'][:12]}): pass it with --model")
        if given[kind]["sha256"] != record["sha256"]:
            raise SeqvprError(f"--model {given[kind]['folder']} is not the {kind} model {folder} was built with "
                              f"({record['folder']}, sha256 {record['sha256'][:12]})")
    extra = [kind for kind in given if kind not in built and kind != "seqmatchnet"]
    if extra:
        raise SeqvprError(f"{folder} was built without the {extra[0]} model {given[extra[0]]['folder']}: its frames "
                          "are another descriptor's (build the map with it)")
    if "seqmatchnet" in built and METHODS[method].family != "matching":
        raise SeqvprError(f"{folder} holds SeqMatchNet-transformed frames, which --method {method} does not use: "
                          "build the map without the SeqMatchNet model and give it to seqvpr match")


def describe_query(
    query: Traversal, saved: SavedMap, models: Mapping[str, TrainedModel], device: str = "cpu",
    progress: ProgressFactory | None = None, **extraction: Any,
) -> Traversal:
    """The query's frames as the map's: described with the map's settings (its transform applied), same dimension."""
    info = saved.info
    if query.descriptors is None and info.description["descriptor"] == "file":
        raise SeqvprError(f"{saved.folder} holds frames of descriptor files: the query {query.source or query.name} "
                          "must be a descriptor file too, described the same way")
    frames = query if query.descriptors is not None else describe_frames(
        query, FrameDescription.from_json(info.description), models, device, progress, **extraction)
    if "seqmatchnet" in (info.model or {}):
        frames = transformed_by(frames, models, device)
    assert frames.descriptors is not None
    if frames.descriptors.shape[1] != info.dim:
        raise SeqvprError(f"{query.source or query.name} has {frames.descriptors.shape[1]}-D descriptors, "
                          f"{saved.folder} holds {info.dim}-D {info.description['descriptor']} frames")
    return frames


@dataclass(frozen=True)
class PreparedQuery:
    """A query ready to match against a map: its frames described as the map's, and the method and models left
    to apply (a map of SeqMatchNet-transformed frames has already had the transform: it matches plainly)."""

    frames: Traversal
    method: str
    models: dict[str, TrainedModel]


def prepare_query(
    saved: SavedMap, query: Traversal, method: str, settings: MatchSettings,
    models: Mapping[str, TrainedModel] | None = None, rerank: int = 0, progress: ProgressFactory | None = None,
    **extraction: Any,
) -> PreparedQuery:
    """The query described as ``saved``'s frames, after checking the method, the models and the normalisation
    against the map's (once for a sharded map: its shards share one description)."""
    models = dict(models or {})
    check_run(method, models, rerank)
    check_map_models(saved.info, str(saved.folder), method, models)
    if saved.info.normalized != settings.normalize:
        built = "normalised" if saved.info.normalized else "not normalised"
        raise SeqvprError(f"{saved.folder} holds {built} descriptors: match it with normalisation "
                          f"{'on' if saved.info.normalized else 'off (--no-normalize)'}")
    frames = describe_query(query, saved, models, settings.device, progress, **extraction)
    if "seqmatchnet" in (saved.info.model or {}):  # the map holds transformed frames and so does the query now
        models.pop("seqmatchnet")
        method = "matching" if method == "seqmatchnet" else method
    return PreparedQuery(frames, method, models)


def match_map(
    saved: SavedMap,
    query: Traversal,
    method: str,
    settings: MatchSettings,
    models: Mapping[str, TrainedModel] | None = None,
    *,
    index: str = "flat",
    rerank: int = 0,
    shortlist: int = 0,
    history: int = 0,
    nprobe: int = 16,
    progress: ProgressFactory | None = None,
    search: Mapping[str, Any] | None = None,
    **extraction: Any,
) -> MatchResult:
    """Top-K map frames per query frame by ``method``: what matching the map's sources directly gives; with
    ``shortlist`` S, a frame-matching method re-ranks the candidates the map's index gives (S a query frame; the
    ``history`` query frames before each window place candidates too)."""
    ensure_policy()  # the one thread policy (seqvpr.threads)
    progress = or_logged(progress)  # a Python caller's progress goes to the seqvpr logger
    prepared = prepare_query(saved, query, method, settings, models, rerank, progress, **extraction)
    return match_prepared(saved, prepared, settings, index=index, rerank=rerank, shortlist=shortlist,
                          history=history, nprobe=nprobe, progress=progress, search=search)


def match_prepared(
    saved: SavedMap, prepared: PreparedQuery, settings: MatchSettings, *, index: str = "flat", rerank: int = 0,
    shortlist: int = 0, history: int = 0, nprobe: int = 16, progress: ProgressFactory | None = None,
    search: Mapping[str, Any] | None = None,
) -> MatchResult:
    """``match_map`` on a query already described as the map's frames (``prepare_query``); ``search``: the
    method's own settings (steps, contrast window)."""
    frames, method, models = prepared.frames, prepared.method, prepared.models
    if shortlist:
        check_shortlist(saved, method, models)
        return shortlist_match(saved, frames, method, settings, shortlist, nprobe, history)
    if uses_window_index(saved, method, settings, models, rerank):
        return indexed_retrieval(saved, frames, settings, nprobe)
    return build_matcher(method, settings, models, index=index, rerank=rerank, progress=progress,
                         **(search or {})).topk(saved.frames, frames)


def uses_window_index(saved: SavedMap, method: str, settings: MatchSettings, models, rerank: int) -> bool:
    """A retrieval method whose sequence descriptors the map's index already holds (same method, same centred
    windows of L frames, no model, no re-ranking) searches that index instead of pooling the map again."""
    record = saved.info.index or {}
    spec = settings.sequence
    same_windows = (spec.align, spec.boundary, spec.velocities) == ("centered", "drop", (1.0,))
    indexed = (record.get("model") or {}).get("sha256")
    same_model = (not models) if indexed is None else (
        set(models) == {"seqnet"} and model_record(models["seqnet"].folder)["sha256"] == indexed)
    return (METHODS[method].family == "retrieval" and record.get("over") == f"{METHODS[method].pooling}:{spec.length}"
            and same_windows and same_model and not rerank)


def indexed_retrieval(saved: SavedMap, frames: Traversal, settings: MatchSettings, nprobe: int) -> MatchResult:
    """Top-K map frames per query frame from the map's saved index over its windows' sequence descriptors."""
    import numpy as np
    import torch

    from seqvpr.maps.index import open_frame_index, window_search
    from seqvpr.sequences.matching import unit_rows
    from seqvpr.sequences.topk import TopK

    query = unit_rows(torch.as_tensor(np.asarray(frames.descriptors, dtype=np.float32)))
    index = open_frame_index(saved, nprobe)
    rows, distances = window_search(saved, index, query, frames.segment_ids, min(settings.k, index.ntotal))
    return MatchResult(saved.frames, frames, TopK(rows, distances, rows[:, 0] >= 0), settings)


def check_shortlist(saved: SavedMap, method: str, models: Mapping[str, TrainedModel]) -> None:
    """A shortlist serves the frame-matching methods, over the frames the map's index holds."""
    if METHODS[method].family != "matching":
        raise SeqvprError(f"--shortlist applies to the frame-matching methods (single, matching, seqmatchnet), "
                          f"not --method {method}")
    if "seqmatchnet" in models:
        raise SeqvprError(f"--shortlist with a SeqMatchNet model needs a map built through it: {saved.folder}'s "
                          "index holds untransformed frames")


def shortlist_match(
    saved: SavedMap, frames: Traversal, method: str, settings: MatchSettings, shortlist: int, nprobe: int,
    history: int = 0,
) -> MatchResult:
    """Shortlisted frame matching: candidates from the map's faiss index, re-ranked by exact sequence distance
    (``rerank``). An index over frames: each query frame's ``shortlist`` nearest map frames place candidate windows
    (``frame_shortlist``, up to (L + history) x S); over windows: each query window's ``shortlist`` nearest ones."""
    query, settings = shortlist_query(frames, method, settings)
    over = index_over(saved, history)
    vectors = int(saved.info.index.get("ntotal", saved.info.count))
    shortlist, history = shortlist_size(shortlist, history, vectors, len(frames), settings)
    found = index_neighbours(saved, query, frames.segment_ids, shortlist, nprobe)
    candidates = shortlist_candidates(found, over, frames.segment_ids, settings.sequence, saved.info.count, history)
    top = rerank_candidates(saved, query, candidates, settings, frames.segment_ids)
    return MatchResult(saved.frames, frames, top, settings, shortlist=candidates)


def shortlist_size(shortlist: int, history: int, vectors: int, n_query: int, settings: MatchSettings
                   ) -> tuple[int, int]:
    """The shortlist S and history H a search uses: S clipped to the index's ``vectors`` and H to the query's
    frames (more finds nothing more: the result is the same), then the candidate table, n_query x (L + H) x S rows,
    checked against ``settings.memory_budget`` before any search (one line naming the options)."""
    shortlist, history = min(shortlist, max(vectors, 1)), min(history, n_query)
    cost = n_query * (settings.sequence.length + history) * shortlist * 8 * 3  # neighbours, candidates, sorting
    if settings.memory_budget is not None and cost > settings.memory_budget:
        raise SeqvprError(f"--shortlist {shortlist} with --shortlist-history {history} and -L "
                          f"{settings.sequence.length}: the candidates of {n_query} queries need {cost / 2**20:.0f} "
                          f"MiB, over the --memory-budget of {settings.memory_budget / 2**20:.0f} MiB (lower them)")
    return shortlist, history


def shortlist_query(frames: Traversal, method: str, settings: MatchSettings):
    """The query's frame descriptors as a tensor (normalised if asked) and the settings a shortlisted match uses
    (one-frame windows for ``single``)."""
    import numpy as np
    import torch

    from seqvpr.sequences.matching import unit_rows
    from seqvpr.sequences.windows import SequenceSpec

    spec = SequenceSpec(1) if METHODS[method].length == 1 else settings.sequence
    query = torch.as_tensor(np.asarray(frames.descriptors, dtype=np.float32))
    return (unit_rows(query) if settings.normalize else query), replace(settings, sequence=spec)


def index_over(saved: SavedMap, history: int = 0) -> str:
    """What the map's index holds vectors of (``frames``, or ``METHOD:L`` windows); history needs frames."""
    if not saved.info.index:
        raise SeqvprError(f"{saved.folder} has no index: add one with seqvpr map index {saved.folder} --index SPEC")
    over = saved.info.index["over"]
    if history and over != "frames":
        raise SeqvprError(f"--shortlist-history needs an index over frames; {saved.folder}'s is over {over}")
    return over


def index_neighbours(saved: SavedMap, query, segments, width: int, nprobe: int) -> TopK:
    """The ``width`` nearest map rows of each query frame (an index over frames) or window (over windows), by the
    map's index: rows and Euclidean distances, -1 / +inf where none."""
    from seqvpr.maps.index import open_frame_index, search_frames, window_search
    from seqvpr.sequences.topk import TopK

    index = open_frame_index(saved, nprobe)
    if saved.info.index["over"] == "frames":
        rows, distances = search_frames(index, query.numpy(), width)
    else:  # each query window's sequence descriptor finds its candidate frames directly
        rows, distances = window_search(saved, index, query, segments, width)
    return TopK(rows, distances, rows[:, 0] >= 0)


def shortlist_candidates(found: TopK, over: str, segments, spec, count: int, history: int = 0) -> TopK:
    """The candidate windows of each query: from its frames' neighbours (``frame_shortlist``, an index over frames)
    or its window's own (over windows)."""
    from seqvpr.sequences.hierarchical import frame_shortlist
    from seqvpr.sequences.topk import TopK
    from seqvpr.sequences.windows import window_starts

    starts = window_starts(segments, spec.length, spec.offset, spec.boundary)
    if over == "frames":
        return frame_shortlist(found.indices, starts, spec, count, history=history, query_segments=segments)
    return TopK(found.indices, found.distances, starts >= 0)


def rerank_candidates(saved: SavedMap, query, candidates: TopK, settings: MatchSettings, segments) -> TopK:
    """The candidates re-ordered by exact sequence distance over the map's rows (only candidate rows are read: a
    view of the memory map, or coded rows decoded), the best K kept."""
    import numpy as np
    import torch

    from seqvpr.sequences.hierarchical import rerank

    stored = saved.descriptors
    reference = torch.from_numpy(stored) if isinstance(stored, np.ndarray) else stored
    return rerank(query, reference, candidates, settings.sequence, segments, saved.frames.segment_ids,
                  k=settings.k)


def shortlist_recall(result: MatchResult, gt) -> float | None:
    """The share of scored queries whose shortlist holds a true place (what the approximation can still find)."""
    from seqvpr.evaluation.metrics import evaluate

    if result.shortlist is None:
        return None
    candidates = result.shortlist
    width = candidates.indices.shape[1]
    return evaluate(candidates.indices, candidates.distances, candidates.has_window, gt, (width,)).recall[width]
