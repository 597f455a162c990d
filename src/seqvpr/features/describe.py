"""Describing traversals: frame descriptors from images (patch-normalised thumbnails, a backbone, a user's
exported encoder), kept as they are when a traversal already has them; both sides at once, PCA-whitening."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from seqvpr.data.traversal import Traversal
from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.features.extraction import (
    BACKBONES,
    FILE_ENCODERS,
    TORCHSCRIPT,
    Extractor,
    ExtractorConfig,
    build_extractor,
    extract_descriptors,
    init_netvlad,
)
from seqvpr.features.patchnorm import PatchNormConfig, patchnorm_extraction
from seqvpr.features.whitening import fit_pca_whitening
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
    engine: str = "auto",
) -> Traversal:
    """The traversal with descriptors: kept if it has them, else computed from its images.

    ``descriptor`` is ``patchnorm`` (weight-free thumbnails, ``config``), a backbone name (with ``extractor``'s
    weights, pooling and input size; ``model``, if given, is that extractor already built, e.g. a NetVLAD head
    from ``netvlad_extractor``) or ``torchscript:PATH``, a user's exported encoder (``extractor``'s input size,
    mean and std). With ``skip_bad`` unreadable images are dropped from the traversal. ``engine`` runs a network
    (``features.engines``: torch, onnx, or auto: ONNX Runtime on the CPU where the encoder exports).
    """
    ensure_policy()  # the one thread policy (seqvpr.threads)
    check_extraction_settings(cache_dir, skip_bad, engine)
    if traversal.descriptors is not None:
        return traversal
    if descriptor != "patchnorm":
        extractor = descriptor_config(descriptor, extractor)  # an unknown name fails before any image is read
    assert traversal.image_paths is not None
    tick = progress(len(traversal), f"describe {traversal.name}") if progress else None
    if descriptor == "patchnorm":
        if cache_dir is not None:
            raise SettingError("{cache_dir} applies to backbone descriptors: patch-normalised thumbnails are not cached "
                              "(they cost about what reading the cache would)")
        rows, kept = patchnorm_extraction(traversal.image_paths, config, tick, skip_bad)
        kept_traversal = traversal if len(kept) == len(traversal) else traversal.select(kept)
        return kept_traversal.with_descriptors(rows)
    extraction = extract_descriptors(traversal.image_paths, extractor, device=device, cache_dir=cache_dir,
                                     skip_bad=skip_bad, progress=tick, extractor=model, engine=engine)
    kept = traversal if len(extraction.rows) == len(traversal) else traversal.select(extraction.rows)
    return kept.with_descriptors(extraction.descriptors)


def check_extraction_settings(cache_dir: Any = None, skip_bad: Any = False, engine: Any = "auto") -> None:
    """``describe``'s settings every entry point takes alike: a cache folder path (or None), a flag and an engine."""
    from seqvpr.features.engines import check_engine

    check_engine(engine)
    checks.flag(skip_bad, "skip_bad")
    if cache_dir is not None:
        checks.a_path(cache_dir, "cache_dir")


def descriptor_config(descriptor: str, extractor: ExtractorConfig) -> ExtractorConfig:
    """The extractor configuration of a descriptor name (a backbone, or ``torchscript:PATH``: that file), the
    rest from ``extractor``; an unknown name is a one-line error."""
    for kind in FILE_ENCODERS:  # ``torchscript:PATH``, ``onnx:PATH``
        if descriptor.startswith(f"{kind}:") and descriptor != f"{kind}:":
            return replace(extractor, backbone=kind, weights=descriptor.removeprefix(f"{kind}:"))
    if descriptor not in BACKBONES:
        raise SeqvprError(f"descriptor {descriptor!r} is not known (choose from: {', '.join(DESCRIPTORS)}, "
                          f"{TORCHSCRIPT_PREFIX}PATH, onnx:PATH)")
    return replace(extractor, backbone=descriptor)


def dropped_frames(original: Traversal, kept: Traversal) -> list[str]:
    """Names of the frames of ``original`` that ``kept`` lacks (images ``describe(skip_bad=True)`` dropped)."""
    present = set(int(i) for i in kept.frame_index)
    names = original.frame_names()
    return [names[row] for row, i in enumerate(original.frame_index) if int(i) not in present]


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
