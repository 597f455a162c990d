"""Stage functions around a match: describing traversals, ground truth, scoring a result.

    reference, query = load_traversal(...), load_traversal(...)
    reference, query = describe(reference), describe(query)      # images -> descriptors when needed
    result = build_matcher("matching", MatchSettings(SequenceSpec(length=5))).topk(reference, query)
    scores = evaluate_match(result, ground_truth(reference, query, parse_radius("2f")))
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from seqvpr.data.groundtruth import GroundTruth, Radius, ground_truth_within_radius
from seqvpr.data.loaders.ground_truth_files import load_ground_truth_file
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError, SeqvprWarning
from seqvpr.evaluation.metrics import DEFAULT_KS, Evaluation, NoPositivePolicy, evaluate
from seqvpr.features.extraction import (
    BACKBONES,
    TORCHSCRIPT,
    Extractor,
    ExtractorConfig,
    build_extractor,
    extract_descriptors,
    init_netvlad,
)
from seqvpr.features.patchnorm import PatchNormConfig, patchnorm_extraction
from seqvpr.features.whitening import fit_pca_whitening
from seqvpr.matchers.base import MatchResult, MatchSettings
from seqvpr.matchers.frames import query_rows
from seqvpr.sequences.matching import frame_distances, sequence_distance_matrix
from seqvpr.progress import ProgressFactory
from seqvpr.threads import ensure_policy

DESCRIPTORS = ("patchnorm", *BACKBONES)
TORCHSCRIPT_PREFIX = f"{TORCHSCRIPT}:"  # ``torchscript:PATH``: a user's exported encoder


def describe(
    traversal: Traversal,
    descriptor: str = "patchnorm",
    config: PatchNormConfig = PatchNormConfig(),
    progress: ProgressFactory | None = None,
    *,
    extractor: ExtractorConfig = ExtractorConfig(),
    device: str = "cpu",
    cache_dir: str | Path | None = None,
    skip_bad: bool = False,
    model: Extractor | None = None,
) -> Traversal:
    """The traversal with descriptors: kept if it has them, else computed from its images.

    ``descriptor`` is ``patchnorm`` (weight-free thumbnails, ``config``), a backbone name (with ``extractor``'s
    weights, pooling and input size; ``model``, if given, is that extractor already built, e.g. a NetVLAD head
    from ``netvlad_extractor``) or ``torchscript:PATH``, a user's exported encoder (``extractor``'s input size,
    mean and std). With ``skip_bad`` unreadable images are dropped from the traversal.
    """
    ensure_policy()  # the one thread policy (seqvpr.threads)
    if traversal.descriptors is not None:
        return traversal
    if descriptor != "patchnorm":
        extractor = descriptor_config(descriptor, extractor)  # an unknown name fails before any image is read
    assert traversal.image_paths is not None
    tick = progress(len(traversal), f"describe {traversal.name}") if progress else None
    if descriptor == "patchnorm":
        if cache_dir is not None:
            raise SeqvprError("--cache-dir applies to backbone descriptors: patch-normalised thumbnails are not cached "
                              "(they cost about what reading the cache would)")
        rows, kept = patchnorm_extraction(traversal.image_paths, config, tick, skip_bad)
        kept_traversal = traversal if len(kept) == len(traversal) else traversal.select(kept)
        return kept_traversal.with_descriptors(rows)
    extraction = extract_descriptors(traversal.image_paths, extractor, device=device, cache_dir=cache_dir,
                                     skip_bad=skip_bad, progress=tick, extractor=model)
    kept = traversal if len(extraction.rows) == len(traversal) else traversal.select(extraction.rows)
    return kept.with_descriptors(extraction.descriptors)


def descriptor_config(descriptor: str, extractor: ExtractorConfig) -> ExtractorConfig:
    """The extractor configuration of a descriptor name (a backbone, or ``torchscript:PATH``: that file), the
    rest from ``extractor``; an unknown name is a one-line error."""
    if descriptor.startswith(TORCHSCRIPT_PREFIX) and descriptor != TORCHSCRIPT_PREFIX:
        return replace(extractor, backbone=TORCHSCRIPT, weights=descriptor.removeprefix(TORCHSCRIPT_PREFIX))
    if descriptor not in BACKBONES:
        raise SeqvprError(f"descriptor {descriptor!r} is not known (choose from: {', '.join(DESCRIPTORS)}, "
                          f"{TORCHSCRIPT_PREFIX}PATH)")
    return replace(extractor, backbone=descriptor)


def dropped_frames(original: Traversal, kept: Traversal) -> list[str]:
    """Names of the frames of ``original`` that ``kept`` lacks (images ``describe(skip_bad=True)`` dropped)."""
    present = set(int(i) for i in kept.frame_index)
    names = original.frame_names()
    return [names[row] for row, i in enumerate(original.frame_index) if int(i) not in present]


def kept_rows(original: Traversal, kept: Traversal) -> np.ndarray:
    """Rows of ``original`` that ``kept`` holds, ``kept`` being a subsequence of it (what ``describe(skip_bad=True)``
    leaves)."""
    same = ((lambda a, b: original.image_paths[a] == kept.image_paths[b]) if original.image_paths and kept.image_paths
            else (lambda a, b: original.frame_index[a] == kept.frame_index[b]))
    rows, j = [], 0
    for row in range(len(original)):
        if j < len(kept) and same(row, j):
            rows.append(row)
            j += 1
    return np.asarray(rows, dtype=np.int64)


def ground_truth_of_kept(gt: GroundTruth, pair: tuple[Traversal, Traversal], kept: tuple[Traversal, Traversal]) -> GroundTruth:
    """The ground truth of the frames left after unreadable images were skipped (itself when none was)."""
    (reference, query), (kept_reference, kept_query) = pair, kept
    if len(reference) == len(kept_reference) and len(query) == len(kept_query):
        return gt
    return gt.restrict(kept_rows(query, kept_query), kept_rows(reference, kept_reference))


def describe_pair(
    reference: Traversal,
    query: Traversal,
    descriptor: str = "patchnorm",
    config: PatchNormConfig = PatchNormConfig(),
    progress: ProgressFactory | None = None,
    **extraction,
) -> tuple[Traversal, Traversal]:
    """Both traversals with descriptors (``describe``'s options); a NetVLAD head is initialised once, on the
    reference images (the query's when only it has images), and shared by both."""
    extractor = extraction.get("extractor")
    if descriptor != "patchnorm" and extractor is not None and extractor.pooling == "netvlad":
        extractor = descriptor_config(descriptor, extractor)  # the backbone the descriptor names
        images = reference.image_paths if reference.image_paths is not None else query.image_paths
        if images is not None:
            extraction["model"] = netvlad_extractor(extractor, images, extraction.get("device", "cpu"), progress)
    return (describe(reference, descriptor, config, progress, **extraction),
            describe(query, descriptor, config, progress, **extraction))


def netvlad_extractor(
    config: ExtractorConfig,
    images: Sequence[Path],
    device: str = "cpu",
    progress: ProgressFactory | None = None,
    seed: int = 0,
) -> Extractor:
    """A backbone + NetVLAD extractor whose clusters are k-means of the local features of ``images`` (seeded)."""
    if config.pooling != "netvlad":
        raise SeqvprError(f"netvlad_extractor needs pooling 'netvlad', got {config.pooling!r}")
    model = build_extractor(config)
    tick = progress(min(len(images), 300), "NetVLAD k-means init") if progress else None
    init_netvlad(model, images, config, device=device, seed=seed, progress=tick)
    return model


def whiten_pair(reference: Traversal, query: Traversal, dim: int) -> tuple[Traversal, Traversal, int]:
    """Both traversals PCA-whitened to ``dim`` dimensions, fitted on the reference (the papers' NetVLAD + PCA-W);
    ``dim`` is lowered to what the reference supports (frames - 1, descriptor size). Returns the dimension used."""
    if reference.descriptors is None or query.descriptors is None:
        raise SeqvprError("PCA-whitening needs descriptors on both traversals (describe() the images first)")
    used = min(dim, len(reference) - 1, reference.descriptors.shape[1])
    whitening = fit_pca_whitening(reference.descriptors, used)
    return (reference.with_descriptors(whitening.apply(reference.descriptors)),
            query.with_descriptors(whitening.apply(query.descriptors)), used)


def distance_matrix(reference: Traversal, query: Traversal, settings: MatchSettings = MatchSettings()) -> np.ndarray:
    """The full sequence-distance matrix [n_query, n_reference] (+inf where a window is missing), for plots and
    small traversals; ``match_traversals`` keeps only the top K and never holds it."""
    ref, qry = query_rows(reference, settings), query_rows(query, settings)
    full = sequence_distance_matrix(frame_distances(qry, ref), settings.sequence, query.segment_ids, reference.segment_ids)
    return full.double().cpu().numpy()


def ground_truth(
    reference: Traversal, query: Traversal, radius: Radius | None = None, file: str | Path | None = None,
    layout: str | None = None,
) -> GroundTruth:
    """Positives between the rows of two traversals, from a radius or from a GT file over source indices (a dense
    matrix file oriented by ``layout``, else by the traversals' sizes)."""
    if file is not None:
        gt = load_ground_truth_file(file, source_frames(query), source_frames(reference), layout)
        return gt.restrict(query.frame_index, reference.frame_index)
    if radius is None:
        if reference.positions is not None and query.positions is not None:
            radius = Radius(25.0, "m")
        else:
            raise SeqvprError("frame-aligned traversals need a frame radius, e.g. --radius 2f (or a --ground-truth file)")
    return ground_truth_within_radius(query, reference, radius)


def resolve_ground_truth(
    reference: Traversal, query: Traversal, radius: str | None = None, file: str | Path | None = None,
    description: str | Path | None = None, whole: bool = False, layout: str | None = None,
) -> GroundTruth:
    """Ground truth from a file, a radius (``25m``, ``2f``), or else the ``[ground_truth]`` table of a description
    file (``dataset.toml``) the reference came from. Both a radius and a file is an error; ``whole`` traversals (no
    ``--frames`` cut) must be the file's size."""
    from seqvpr.data.groundtruth import parse_radius
    from seqvpr.data.sources import ground_truth_spec

    if radius and file:
        raise SeqvprError(f"give --radius or --ground-truth, not both: {file} decides which frames match")
    spec = ground_truth_spec(description) if description is not None else None
    if file is None and radius is None and spec is not None:
        return ground_truth(reference, query, spec.radius, spec.file)
    if file is not None and whole:
        check_ground_truth_covers(load_ground_truth_file(file, source_frames(query), source_frames(reference), layout),
                                  reference, query, file)
    return ground_truth(reference, query, parse_radius(radius) if radius else None, file, layout)


def source_frames(traversal: Traversal) -> int:
    """Frames of the source a traversal was read from, as far as it shows (its last frame number + 1)."""
    return int(traversal.frame_index.max()) + 1 if len(traversal) else 0


def check_ground_truth_covers(gt: GroundTruth, reference: Traversal, query: Traversal, file) -> None:
    """Warn when a ground-truth file for whole traversals names frames they lack: their positives are dropped (a
    file for another data set, or a known quirk such as Gardens Point's VPR-Bench file with 202 reference columns)."""
    import warnings

    for what, axis, traversal in (("query", 0, query), ("reference", 1, reference)):
        frames = int(traversal.frame_index.max()) + 1 if len(traversal) else 0
        named = gt.positives.nonzero()[axis]
        beyond = np.unique(named[named >= frames])
        if len(beyond):
            warnings.warn(f"{file} names {len(beyond)} {what} frames the {what} traversal lacks ({int(beyond[0])}"
                          f"{'' if len(beyond) == 1 else f'..{int(beyond[-1])}'}; it has {frames}): their positives "
                          "are ignored", SeqvprWarning, stacklevel=3)


def evaluate_match(
    result: MatchResult, gt: GroundTruth, ks: Sequence[int] = DEFAULT_KS, no_positive: NoPositivePolicy = "exclude",
    uniqueness: int | None = None,
) -> Evaluation:
    """Recall@K and PR of a match result, and the precision of its top-1 matches' per-frame correspondences. With
    ``uniqueness`` E, PR ranks the queries by SeqSLAM's windowed uniqueness (exclusion E frames), not by distance."""
    from seqvpr.evaluation.metrics import frame_precision, uniqueness_margins

    top = result.topk
    scores = top.distances
    if uniqueness is not None:
        scores = uniqueness_margins(top.indices, top.distances, uniqueness)[:, None]
    evaluation = evaluate(top.indices, scores, top.has_window, gt, ks, no_positive)
    pairs = match_correspondences(result)
    return evaluation if pairs is None else replace(evaluation, frame_precision=frame_precision(*pairs, gt))


def match_correspondences(result: MatchResult) -> tuple[np.ndarray, np.ndarray] | None:
    """The per-frame correspondences (query rows, reference rows [n_query, L]) of a result's top-1 matches: the
    matcher's own (an adaptive path), else the windows' alignment at slope 1 (None with other velocities)."""
    from seqvpr.sequences.correspondences import window_correspondences

    if result.correspondences is not None:
        return result.correspondences
    spec = result.settings.sequence
    if tuple(spec.velocities) != (1.0,) or result.topk.indices.shape[1] == 0:
        return None
    return window_correspondences(result.topk.indices[:, 0], spec, result.query.segment_ids,
                                  result.reference.segment_ids)
