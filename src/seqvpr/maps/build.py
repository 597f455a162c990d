"""Building a map: sources described once (descriptor files as they are, images through a descriptor or an image
model, optionally through a SeqMatchNet transform), laid end to end and saved (``files.write_map``).

The same ``FrameDescription`` describes a query later, so a query is always described as its map was.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr import checks
from seqvpr.arrays import file_mapped, release_pages
from seqvpr.data.sources import load_traversal
from seqvpr.data.geo import positions_in
from seqvpr.data.traversal import Traversal, parse_frame_range, slice_frame_range
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.features.extraction import ExtractorConfig
from seqvpr.features.patchnorm import PatchNormConfig
from seqvpr.io import atomic_folder, check_output_apart
from seqvpr.maps.keep import keep_users_files
from seqvpr.maps.files import (
    MapSource,
    INFO_FILE,
    MapInfo,
    SavedMap,
    ShardedMap,
    open_map,
    write_map,
)
from seqvpr.maps.sharding import DEFAULT_OVERLAP, write_sharded_map
from seqvpr.maps.index import model_record
from seqvpr.matchers.rows import transformed_by
from seqvpr.methods import image_model
from seqvpr.models.registry import TrainedModel
from seqvpr.features.describe import check_extraction_settings, describe
from seqvpr.progress import ProgressFactory
from seqvpr.sequences.matching import unit_rows
from seqvpr.progress import progress_or_log
from seqvpr.threads import ensure_policy

#: model kinds whose output a map stores: image encoders (the frames) and SeqMatchNet (the transformed frames)
STORED_KINDS = ("jist", "cosplace", "seqmatchnet")


@dataclass(frozen=True)
class FrameDescription:
    """How images become frame descriptors: ``patchnorm``, a backbone or ``torchscript:PATH`` with their settings
    (an image model given at build time describes them instead, at ``image_size``)."""

    descriptor: str = "patchnorm"
    patchnorm: PatchNormConfig = field(default_factory=PatchNormConfig)
    extractor: ExtractorConfig = field(default_factory=ExtractorConfig)
    image_size: tuple[int, int] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"descriptor": self.descriptor, "patchnorm": asdict(self.patchnorm), "extractor": asdict(self.extractor),
                "image_size": None if self.image_size is None else list(self.image_size)}

    @classmethod
    def from_json(cls, values: dict[str, Any]) -> FrameDescription:
        """The description ``map.json`` records; a missing or unknown field is a one-line error."""
        try:
            extractor = {k: tuple(v) if isinstance(v, list) else v for k, v in values["extractor"].items()}
            size = values.get("image_size")
            return cls(values["descriptor"], PatchNormConfig(**values["patchnorm"]), ExtractorConfig(**extractor),
                       None if size is None else (int(size[0]), int(size[1])))
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise SeqvprError(f"map.json: malformed frame description ({type(error).__name__}: {error})") from None


def describe_frames(
    traversal: Traversal,
    description: FrameDescription,
    models: Mapping[str, TrainedModel],
    device: str = "cpu",
    progress: ProgressFactory | None = None,
    **extraction: Any,
) -> Traversal:
    """Frame descriptors of one traversal: kept when it holds them, else its images through the image model among
    ``models`` (JIST's encoder, CosPlace) or ``description``'s descriptor (``extraction``: cache_dir, skip_bad)."""
    if traversal.descriptors is not None:
        return traversal
    model = image_model(models)
    if model is not None:
        from seqvpr.models.jist import describe_images

        width, height = description.image_size or model.image_size
        return describe_images(model.module, traversal, width, height, device, engine=extraction.get("engine", "auto"))
    if description.extractor.pooling == "netvlad":
        raise SeqvprError("a map cannot use NetVLAD pooling yet (its clusters are fitted to one run's images)")
    return describe(traversal, description.descriptor, description.patchnorm, progress,
                    extractor=description.extractor, device=device, **extraction)


def with_default_cache(description: FrameDescription, models: Mapping[str, TrainedModel],
                       extraction: dict[str, Any]) -> dict[str, Any]:
    """``extraction`` with the descriptor cache folder (``seqvpr.cache``) when none is given and a network describes
    the frames: rebuilding a map, or building one from frames already described, reads them back. A cache folder
    that cannot be created is a warning, not a failure: the frames are described without it."""
    if extraction.get("cache_dir") is not None or description.descriptor == "patchnorm" or image_model(models):
        return extraction
    import warnings

    from seqvpr.cache import cache_folder, writable_folder
    from seqvpr.errors import SeqvprWarning

    try:
        return {**extraction, "cache_dir": writable_folder(cache_folder("descriptors"))}
    except SeqvprError as error:
        warnings.warn(f"{error}; describing without a cache", SeqvprWarning)
        return extraction


def model_records(models: Mapping[str, TrainedModel]) -> dict[str, Any] | None:
    """What ``map.json`` says of the models a map's frames went through: kind, folder and weights' sha256."""
    stored = {kind: models[kind] for kind in STORED_KINDS if kind in models}
    if not stored:
        return None
    return {kind: model_record(m.folder) for kind, m in stored.items()}


def build_map(
    sources: Sequence[str],
    out: str | Path,
    description: FrameDescription = FrameDescription(),
    models: Mapping[str, TrainedModel] | None = None,
    *,
    dtype: str = "float32",
    normalize: bool = True,
    device: str = "cpu",
    progress: ProgressFactory | None = None,
    frames: str | None = None,
    indexed: Callable[[SavedMap], object] | None = None,
    thumbnails: bool = False,
    **extraction: Any,
) -> SavedMap:
    """Describe every source (``described_map``) and save the frames as one map. ``indexed`` (e.g. ``add_index``)
    runs on the new map before it replaces anything at ``out``, so a failed index leaves the previous map as it
    was. ``thumbnails`` keeps each frame's thumbnail in the map (sources of images only)."""
    sources = checked_sources(sources, out, models)
    check_build_settings(description, dtype, normalize, device, progress, frames, indexed, extraction)
    checks.flag(thumbnails, "thumbnails")
    whole, info = described_map(sources, Path(out).name, description, models, dtype=dtype, normalize=normalize,
                                device=device, progress=progress, frames=frames, **extraction)
    if thumbnails and whole.image_paths is None:
        raise SettingError(f"{{thumbnails}}: {', '.join(map(str, sources))} hold descriptors, not images; a map keeps "
                           "thumbnails of image sources")
    write_indexed_map(Path(out), whole, info, indexed, thumbnails)
    return open_map(out)


def build_sharded_map(
    sources: Sequence[str],
    out: str | Path,
    shards: int,
    overlap: int = DEFAULT_OVERLAP,
    description: FrameDescription = FrameDescription(),
    models: Mapping[str, TrainedModel] | None = None,
    *,
    dtype: str = "float32",
    normalize: bool = True,
    device: str = "cpu",
    progress: ProgressFactory | None = None,
    frames: str | None = None,
    indexed: Callable[[ShardedMap], object] | None = None,
    **extraction: Any,
) -> ShardedMap:
    """``build_map``, written straight as ``shards`` shard maps overlapping by ``overlap`` frames
    (``shards.write_sharded_map``: never the whole map first); ``indexed`` (e.g. ``index_shards``) runs on them
    before they replace anything at ``out``."""
    sources = checked_sources(sources, out, models)
    check_build_settings(description, dtype, normalize, device, progress, frames, indexed, extraction)
    whole, info = described_map(sources, Path(out).name, description, models, dtype=dtype, normalize=normalize,
                                device=device, progress=progress, frames=frames, **extraction)
    return write_sharded_map(out, whole, info, shards, overlap, indexed)


def checked_sources(sources: Sequence[str] | str | Path, out: str | Path,
                    models: Mapping[str, TrainedModel] | None = None) -> list[str]:
    """The sources as a list (one path given alone is one source, not its characters), none of them and no model
    folder where the map is written (``io.check_output_apart``): checked before any source is read."""
    listed = checks.paths(sources, "sources")
    checks.a_path(out, "out")
    if models is not None:
        checks.instance(models, "models", Mapping, "loaded models by kind (models.registry.load_models)")
        for model in models.values():
            checks.instance(model, "models", TrainedModel, "loaded models by kind (models.registry.load_models)")
    check_output_apart(out, [*listed, *(model.folder for model in (models or {}).values())], "the map")
    return listed


def check_build_settings(description: Any, dtype: Any, normalize: Any, device: Any, progress: Any, frames: Any,
                         indexed: Any, extraction: Mapping[str, Any]) -> None:
    """A map build's settings checked before any source is read (one line naming the argument); ``extraction``
    takes ``describe``'s ``cache_dir`` and ``skip_bad``."""
    unknown = sorted(set(extraction) - {"cache_dir", "skip_bad", "engine"})
    if unknown:
        raise SettingError(f"a map build has no setting {unknown[0]!r} (its extraction settings: {{cache_dir}}, "
                           "skip_bad, {engine})")
    check_extraction_settings(**extraction)
    from seqvpr.maps.codes import parse_storage

    checks.instance(description, "description", FrameDescription, "a FrameDescription")
    try:
        parse_storage(checks.text(dtype, "dtype"))
    except SettingError:
        raise
    except SeqvprError as error:
        raise SettingError(f"{{dtype}}: {error}") from None
    checks.flag(normalize, "normalize")
    checks.device(device)
    checks.function(progress, "progress")
    checks.function(indexed, "indexed")
    if frames is not None:
        parse_frame_range(checks.text(frames, "frames"))


def described_map(sources: Sequence[str], name: str, description: FrameDescription = FrameDescription(),
                  models: Mapping[str, TrainedModel] | None = None, *, dtype: str = "float32", normalize: bool = True,
                  device: str = "cpu", progress: ProgressFactory | None = None, frames: str | None = None,
                  **extraction: Any) -> tuple[Traversal, MapInfo]:
    """Every source described (cut to source frames ``START:STOP`` when ``frames`` is given), passed through a
    SeqMatchNet model if given, laid end to end (each source its own segments) and L2-normalised (as matching does)
    unless told not to: the frames, their rows read a chunk at a time, and the map's ``map.json`` record."""
    ensure_policy()  # the one thread policy (seqvpr.threads)
    progress = progress_or_log(progress)  # a Python caller's progress goes to the seqvpr logger
    models = dict(models or {})
    unusable = [kind for kind in models if kind not in STORED_KINDS]
    if unusable:
        raise SeqvprError(f"a {unusable[0]} model does not describe or transform frames; give it to seqvpr match")
    extraction = with_default_cache(description, models, extraction)
    described = []
    for source in sources:
        traversal = slice_frame_range(load_traversal(source, "reference"), frames)
        traversal = describe_frames(traversal, description, models, device, progress, **extraction)
        described.append(transformed_by(traversal, models, device))
    whole = concatenate_traversals(described, name)
    assert whole.descriptors is not None
    # read a chunk at a time (a memory-mapped source's pages handed back after each), normalised as it is written
    # by the torch operation matching applies to a reference
    rows = UnitRows(paged(whole.descriptors)) if normalize else paged(whole.descriptors)
    recorded = description.descriptor if image_model(models) is None else image_model(models).kind
    info = MapInfo(len(whole), int(rows.shape[1]), dtype, normalize,
                   {**description.to_json(), "descriptor": recorded if whole.image_paths is not None else "file"},
                   map_sources(described, list(sources)), model_records(models))
    return whole.with_descriptors(rows), info


class RowChain:
    """Arrays of one width laid end to end, read like one [N, D] array by slices (nothing is concatenated)."""

    ndim = 2

    def __init__(self, parts: Sequence[Any]) -> None:
        self.parts = list(parts)
        self.starts = np.cumsum([0] + [len(p) for p in self.parts])
        self.shape = (int(self.starts[-1]), int(self.parts[0].shape[1]))
        self.dtype = np.result_type(*(p.dtype for p in self.parts))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: slice) -> np.ndarray:
        start, stop, _ = key.indices(len(self))
        pieces = [np.asarray(part[max(start - lo, 0) : min(stop, hi) - lo])
                  for part, lo, hi in zip(self.parts, self.starts[:-1], self.starts[1:]) if start < hi and stop > lo]
        return np.concatenate(pieces) if pieces else np.zeros((0, self.shape[1]), self.dtype)


class PagedRows:
    """A memory-mapped array read by slices into copies, each slice's pages then handed back
    (``arrays.release_pages``): they stay in the page cache, but not in this process, so reading a
    ten-million-row source end to end does not grow its memory."""

    ndim = 2

    def __init__(self, rows: np.ndarray) -> None:
        self.rows, self.shape, self.dtype = rows, rows.shape, rows.dtype

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: slice) -> np.ndarray:
        view = self.rows[key]
        block = np.array(view)
        release_pages(view)
        return block


def paged(rows: Any) -> Any:
    """``rows`` read through ``PagedRows`` where they are a memory-mapped file (each part of a ``RowChain``)."""
    if isinstance(rows, RowChain):
        return RowChain([paged(part) for part in rows.parts])
    return PagedRows(rows) if isinstance(rows, np.ndarray) and rows.ndim == 2 and file_mapped(rows) else rows


class UnitRows:
    """Rows L2-normalised on access, a block at a time (``unit_rows``: what matching applies to a reference), so a
    map of any size is normalised without a copy of it in memory."""

    ndim = 2
    dtype = np.dtype(np.float32)

    def __init__(self, rows: Any) -> None:
        self.rows, self.shape = rows, (len(rows), int(rows.shape[1]))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: slice) -> np.ndarray:
        import torch

        block = np.array(self.rows[key], dtype=np.float32)  # a copy: the source is never written
        unit_rows(torch.from_numpy(block), out=torch.from_numpy(block))
        return block


def write_indexed_map(out: Path, frames: Traversal, info: MapInfo,
                      indexed: Callable[[SavedMap], object] | None, thumbnails: bool = False) -> None:
    """``write_map``, and ``indexed`` run on the written map, committed to ``out`` as one; what a map there held
    that it did not own (a user's files) is carried over (``keep.keep_users_files``)."""
    with atomic_folder(out, INFO_FILE) as tmp:  # a failed write names out, not the temporary
        write_map(tmp, frames, info, thumbnails=thumbnails)
        if indexed is not None:
            indexed(open_map(tmp))
        keep_users_files(out, tmp)


def concatenate_traversals(traversals: list[Traversal], name: str = "map") -> Traversal:
    """One traversal of several described ones, each keeping its own segments (a window never spans two); their
    descriptors are read through them (``RowChain``), never copied into one array."""
    if not traversals:
        raise SeqvprError("a map needs at least one source")
    dims = {t.descriptors.shape[1] for t in traversals if t.descriptors is not None}
    if any(t.descriptors is None for t in traversals) or len(dims) != 1:
        raise SeqvprError(f"map sources must all be described with one dimension, got {sorted(dims)}")
    if len(traversals) == 1:  # one source: its arrays as they are (a 1M-frame map is not copied)
        only = traversals[0]
        return replace(only, name=name, segment_ids=np.unique(only.segment_ids, return_inverse=True)[1], source=name)
    segments, offset = [], 0
    for t in traversals:
        segments.append(np.unique(t.segment_ids, return_inverse=True)[1] + offset)
        offset = int(segments[-1].max()) + 1
    column = lambda attr: (np.concatenate([getattr(t, attr) for t in traversals])  # noqa: E731
                           if all(getattr(t, attr) is not None for t in traversals) else None)
    images = all(t.image_paths is not None for t in traversals)
    paths = tuple(p for t in traversals for p in t.image_paths) if images else None
    names = tuple(n for t in traversals for n in t.image_names()) if images else None
    positioned = all(t.positions is not None for t in traversals)
    crs = traversals[0].crs if positioned else None  # the first source's frame: the others are expressed in it
    positions = np.concatenate([positions_in(t.positions, t.crs, crs, t.source or t.name) for t in traversals]) \
        if positioned else None
    return Traversal(name, np.concatenate([t.frame_index for t in traversals]), np.concatenate(segments),
                     RowChain([t.descriptors for t in traversals]), paths, positions,
                     column("timestamps"), column("headings"), source=name, names=names, crs=crs)


def map_sources(traversals: list[Traversal], sources: list[str]) -> tuple[MapSource, ...]:
    """The ``sources`` records of traversals laid end to end."""
    firsts = np.cumsum([0] + [len(t) for t in traversals])
    return tuple(MapSource(str(s), t.name, int(f), len(t)) for s, t, f in zip(sources, traversals, firsts))
