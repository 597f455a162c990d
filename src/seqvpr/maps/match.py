"""Matching a query against a saved or a sharded map: the query described as the map's frames were, the models
checked against the ones the map went through, then the method's matcher stacked for the map (``matchers.assemble``:
its shards, its index's shortlist) as for any reference (frame matching reads the map chunk by chunk;
sequence-descriptor methods pool its frames).

Same name as ``seqvpr.cli.match``: matching against a map; the command that calls it there."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.maps.build import FrameDescription, describe_frames, model_records
from seqvpr.maps.files import MapInfo, SavedMap, ShardedMap
from seqvpr.maps.index import model_record
from seqvpr.methods import METHODS, build_matcher, check_run
from seqvpr.models.registry import TrainedModel
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers.rows import transformed_by
from seqvpr.progress import ProgressFactory, progress_or_log
from seqvpr.threads import ensure_policy


def check_map_models(info: MapInfo, folder: str, method: str, models: Mapping[str, TrainedModel]) -> None:
    """The models a map's frames went through must be given again (same weights); an image model it was not built
    with cannot describe its frames. A SeqMatchNet model given to a map built without one transforms both sides at
    match time; a map built through one holds transformed frames, which only the frame-matching methods use."""
    built = info.model or {}
    given = model_records(models) or {}
    for kind, record in built.items():
        if kind not in given:
            raise SettingError(f"{folder} was built through the {kind} model {record['folder']} "
                               f"(sha256 {record['sha256'][:12]}): pass it in {{models}}")
        if given[kind]["sha256"] != record["sha256"]:
            raise SettingError(f"{{models}}: {given[kind]['folder']} is not the {kind} model {folder} was built with "
                               f"({record['folder']}, sha256 {record['sha256'][:12]})")
    extra = [kind for kind in given if kind not in built and kind != "seqmatchnet"]
    if extra:
        raise SeqvprError(f"{folder} was built without the {extra[0]} model {given[extra[0]]['folder']}: its frames "
                          "are another descriptor's (build the map with it)")
    if "seqmatchnet" in built and METHODS[method].family != "matching":
        raise SettingError(f"{folder} holds SeqMatchNet-transformed frames, which {{method}} {method} does not use: "
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
class MapMethod:
    """The method and models left to apply to a query described as a map's frames (a map of SeqMatchNet-transformed
    frames has already had the transform: it matches plainly)."""

    method: str
    models: dict[str, TrainedModel]


def is_map(reference: object) -> bool:
    """Whether a reference is an opened map (saved or sharded), which describes a query as it described its frames."""
    return isinstance(reference, (SavedMap, ShardedMap))


def map_method(saved: SavedMap, method: str, settings: MatchSettings,
               models: Mapping[str, TrainedModel] | None = None, rerank: int = 0) -> MapMethod:
    """The method and models that match a query against ``saved``, after checking the method, the models and the
    normalisation against the map's (once for a sharded map: its shards share one description)."""
    models = dict(models or {})
    check_run(method, models, rerank)
    check_map_models(saved.info, str(saved.folder), method, models)
    if saved.info.normalized != settings.normalize:
        built = "normalised" if saved.info.normalized else "not normalised"
        raise SeqvprError(f"{saved.folder} holds {built} descriptors: match it with normalisation "
                          f"{'on' if saved.info.normalized else 'off (--no-normalize)'}")
    if "seqmatchnet" in (saved.info.model or {}):  # the map holds transformed frames and so will the query
        models.pop("seqmatchnet", None)
        method = "matching" if method == "seqmatchnet" else method
    return MapMethod(method, models)


def match_map(
    reference: SavedMap | ShardedMap,
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
    ranks: Any = None,
    **extraction: Any,
) -> MatchResult | None:
    """Top-K map frames per query frame by ``method``: what matching the map's sources directly gives; with
    ``shortlist`` S, a frame-matching method re-ranks the candidates the map's index gives (S a query frame; the
    ``history`` query frames before each window place candidates too). A sharded map is matched shard by shard
    (under ``torchrun`` each rank its own, merged on rank 0: the other ranks get None); its shards share one
    description, checked and applied once a rank. ``search``: the method's own settings (steps, contrast window)."""
    from seqvpr import distributed
    from seqvpr.matchers.sharded import is_sharded
    from seqvpr.matchers.stack import Shortlist, assemble

    ensure_policy()  # the one thread policy (seqvpr.threads)
    progress = progress_or_log(progress)  # a Python caller's progress goes to the seqvpr logger
    world = ranks or distributed.current()
    described = reference.open_shard(0) if is_sharded(reference) else reference  # the description its frames share
    chosen = distributed.everywhere(lambda: map_method(described, method, settings, models, rerank), world)
    matcher = method_matcher(described, chosen, settings, index=index, rerank=rerank, nprobe=nprobe,
                             progress=progress, search=search)
    listed = None if not shortlist else Shortlist(lambda: map_neighbors(reference, nprobe, history, world),
                                                   shortlist, history)
    stack = distributed.everywhere(lambda: assemble(matcher, reference, listed, world), world)
    frames = distributed.everywhere(lambda: describe_query(query, described, dict(models or {}), settings.device,
                                                           progress, **extraction), world)
    return stack.topk(reference, frames)


def method_matcher(saved: SavedMap, chosen: MapMethod, settings: MatchSettings, *, index: str = "flat",
                   rerank: int = 0, nprobe: int = 16, progress: ProgressFactory | None = None,
                   search: Mapping[str, Any] | None = None) -> Matcher:
    """The family matcher of the chosen method over ``saved`` (or any map described alike, such as its shards): the
    method's own, or a search of each map's own index when it already holds the method's sequence descriptors."""
    if uses_window_index(saved, chosen.method, settings, chosen.models, rerank):
        from seqvpr.maps.index import IndexNeighbors
        from seqvpr.matchers.retrieval import IndexedRetrieval

        matcher = IndexedRetrieval(settings, lambda opened: IndexNeighbors(opened, nprobe))
        matcher.method = chosen.method
        return matcher
    return build_matcher(chosen.method, settings, chosen.models, index=index, rerank=rerank, progress=progress,
                         **(search or {}))


def map_neighbors(reference: SavedMap | ShardedMap, nprobe: int = 16, history: int = 0, ranks: Any = None):
    """The nearest-neighbour search a shortlist over ``reference`` uses: a map's index, or the shards' indexes
    merged into one (each rank searching its shards)."""
    from seqvpr.matchers.sharded import is_sharded

    if is_sharded(reference):
        from seqvpr.maps.sharded_index import ShardedNeighbors

        return ShardedNeighbors(reference, ranks, nprobe, history)
    from seqvpr.maps.index import IndexNeighbors

    return IndexNeighbors(reference, nprobe)


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


def shortlist_recall(result: MatchResult, gt) -> float | None:
    """The share of scored queries whose shortlist holds a true place (what the approximation can still find)."""
    from seqvpr.evaluation.metrics import evaluate

    if result.shortlist is None:
        return None
    candidates = result.shortlist
    width = candidates.indices.shape[1]
    return evaluate(candidates.indices, candidates.distances, candidates.has_window, gt, (width,)).recall[width]
