"""A match's rows: the query's and the reference's descriptors as the kernel reads them (normalised tensors, or a
saved map's rows as stored), one frame's row for a stepper, and the learned per-frame transform (SeqMatchNet)
applied to either side, here only."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.sequences.frame_pass import FrameRow
from seqvpr.sequences.matching import unit_rows

from seqvpr.sequences.match_settings import MatchSettings

if TYPE_CHECKING:
    from seqvpr.models.seqmatchnet import FrameTransform


def query_rows(query: Traversal, settings: MatchSettings) -> torch.Tensor:
    """The query's descriptors as a tensor on the settings' device, L2-normalised per frame when asked."""
    if query.descriptors is None:
        raise SeqvprError(f"{query.source or query.name}: no descriptors (describe() the images first)")
    dtype = {"float32": torch.float32, "float64": torch.float64}[settings.dtype]  # checked by MatchSettings
    try:
        array = query.descriptors
        if not isinstance(array, np.ndarray):  # a saved map's coded rows, decoded
            array = array[:]
        array = np.ascontiguousarray(array) if array.flags.writeable else np.array(array)  # read-only: a copy
        tensor = torch.as_tensor(array, dtype=dtype).to(settings.device)
    except (RuntimeError, AssertionError) as error:
        raise SeqvprError(f"device {settings.device!r} is not usable here ({str(error).splitlines()[0]})") from None
    if settings.normalize:
        tensor = unit_rows(tensor)
    return tensor


def kernel_rows(reference: Reference, settings: MatchSettings):
    """The reference rows the blocked kernel reads: a saved map's as stored (read a chunk at a time; the map was
    normalised as ``settings`` ask, which opening it for a match checks), else a normalised tensor."""
    return reference.descriptors if reference.stored else query_rows(reference, settings)


def whole_rows(reference: Reference, settings: MatchSettings) -> torch.Tensor | np.ndarray:
    """The reference rows a whole-reference pass reads (pooling every window): a saved map's float32 memory map as
    it is, else the rows as a normalised tensor (re-ranking reads ``kernel_rows``: only the candidates' rows)."""
    plain = reference.stored and reference.plain_rows
    return reference.descriptors if plain and settings.dtype == "float32" and settings.device == "cpu" \
        else query_rows(reference, settings)


def check_dimensions(reference: Reference, query: Traversal, ref, qry) -> None:
    """Both sides' descriptors must have one size: one line naming both."""
    if ref.shape[1] != qry.shape[1]:
        raise SeqvprError(f"descriptor dimensions differ: {reference.source or reference.name} has {ref.shape[1]}, "
                          f"{query.source or query.name} has {qry.shape[1]}")


def frame_transform(models: Mapping[str, Any]):
    """The learned per-frame transform among the models (SeqMatchNet's), or None."""
    return models["seqmatchnet"].module if "seqmatchnet" in models else None


def transform_pair(reference: Reference, query: Traversal, transform: FrameTransform | None,
                   device: str = "cpu") -> tuple[Reference, Traversal]:
    """Both sides through a learned per-frame transform (SeqMatchNet), when one is given; else unchanged."""
    if transform is None:
        return reference, query
    return transform_traversal(reference, transform, device), transform_traversal(query, transform, device)


def transformed_by(traversal: Traversal, models: Mapping[str, Any], device: str = "cpu") -> Traversal:
    """A traversal through the SeqMatchNet model among ``models`` (a map's frames as built through it, a query
    described as such a map's), unchanged without one."""
    transform = frame_transform(models)
    return traversal if transform is None else transform_traversal(traversal, transform, device)


def transform_traversal(traversal, model: FrameTransform, device: str = "cpu") -> Traversal:
    """The traversal with its descriptors passed through a learned per-frame transform (e.g. SeqMatchNet)."""
    from seqvpr.models.seqmatchnet import apply_transform

    if traversal.descriptors is None:
        raise SeqvprError(f"{traversal.source or traversal.name}: no descriptors to transform")
    dim = traversal.descriptors.shape[1]
    if dim != model.config.in_dim:
        raise SeqvprError(f"{traversal.source or traversal.name}: the model expects {model.config.in_dim}-D "
                          f"descriptors, these are {dim}-D")
    return traversal.frames.with_descriptors(apply_transform(model, traversal.descriptors, device=device))


def transformed_reference(matcher: Any, reference: Reference) -> Reference:
    """The reference through the matcher's learned per-frame transform, when it has one."""
    transform = getattr(matcher, "transform", None)
    return reference if transform is None else transform_traversal(reference, transform, matcher.settings.device)


def matcher_rows(matcher: Any, reference: Reference):
    """The reference rows a full pass reads: through the matcher's transform, as the kernel reads them."""
    return kernel_rows(transformed_reference(matcher, reference), matcher.settings)


def frame_row(frame, transform=None, normalize: bool = True, out: FrameRow | None = None) -> FrameRow:
    """One query frame's descriptor [D] as ``topk`` prepares a query's rows (float32, transformed, normalised), in
    ``out`` (a row reused frame after frame) or a fresh one."""
    if transform is not None:  # on the transform's device, back to the CPU
        vector = frame if torch.is_tensor(frame) and frame.dtype == torch.float32 else \
            torch.as_tensor(np.asarray(frame, dtype=np.float32))
        device = next(iter(transform.parameters()), vector).device
        with torch.no_grad():
            frame = transform(vector[None].to(device))[0].float().cpu()
    numbers = frame if isinstance(frame, np.ndarray) and frame.dtype == np.float32 else \
        np.asarray(frame.detach().cpu() if torch.is_tensor(frame) else frame, dtype=np.float32)
    if numbers.ndim != 1:
        raise SeqvprError(f"a frame is one descriptor [D], got shape {numbers.shape}")
    out = FrameRow.empty(len(numbers)) if out is None else out
    if len(numbers) != len(out.numbers):
        raise SeqvprError(f"a frame of {len(numbers)} values for a row of {len(out.numbers)}")
    if normalize:
        return out.set_unit(numbers)
    out.numbers[:] = numbers
    return out


def distance_matrix(reference: Traversal, query: Traversal, settings: MatchSettings | None = None) -> np.ndarray:
    """The full sequence-distance matrix [n_query, n_reference] (+inf where a window is missing), for plots and
    small traversals; a matcher's ``topk`` keeps only the top K and never holds it."""
    from seqvpr.sequences.matching import frame_distances, sequence_distance_matrix

    settings = settings or MatchSettings()
    ref, qry = query_rows(reference, settings), query_rows(query, settings)
    full = sequence_distance_matrix(frame_distances(qry, ref), settings.sequence, query.segment_ids, reference.segment_ids)
    return full.double().cpu().numpy()
