"""Matching a query against a saved map: the query described as the map's frames were, the models checked against
the ones the map went through, then ``run_method`` as for any reference (frame matching reads the map chunk by
chunk; sequence-descriptor methods pool its frames)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.maps.build import FrameDescription, describe_frames, model_records
from seqvpr.maps.files import MapInfo, SavedMap
from seqvpr.methods import METHODS, check_run, run_method, transformed_frames
from seqvpr.models.registry import TrainedModel
from seqvpr.pipeline import MatchResult, MatchSettings, ProgressFactory


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
    frames = describe_frames(query, FrameDescription.from_json(info.description), models, device, progress,
                             **extraction)
    if "seqmatchnet" in (info.model or {}):
        frames = transformed_frames(frames, frames, models, device)[0]
    assert frames.descriptors is not None
    if frames.descriptors.shape[1] != info.dim:
        raise SeqvprError(f"{query.source or query.name} has {frames.descriptors.shape[1]}-D descriptors, "
                          f"{saved.folder} holds {info.dim}-D {info.description['descriptor']} frames")
    return frames


def match_map(
    saved: SavedMap,
    query: Traversal,
    method: str,
    settings: MatchSettings,
    models: Mapping[str, TrainedModel] | None = None,
    *,
    index: str = "flat",
    rerank: int = 0,
    progress: ProgressFactory | None = None,
    **extraction: Any,
) -> MatchResult:
    """Top-K map frames per query frame by ``method``: what matching the map's sources directly gives."""
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
    return run_method(method, saved.frames, frames, replace(settings), models, index=index, rerank=rerank,
                      progress=progress)
