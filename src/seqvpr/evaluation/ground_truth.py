"""Ground truth of a match: from a radius, a ground-truth file or a description file's table, for the rows two
traversals hold (after any frames were cut or left out).

Same name as ``seqvpr.data.ground_truth``: ground truth resolved for a match; the type and radii there."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqvpr.data.ground_truth import GroundTruth, Radius, ground_truth_within_radius
from seqvpr.data.loaders.ground_truth_files import load_ground_truth_file
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprWarning, SettingError


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
            raise SettingError("frame-aligned traversals need a frame radius, e.g. {radius} 2f (or a {ground_truth} file)")
    return ground_truth_within_radius(query, reference, radius)


def resolve_ground_truth(
    reference: Traversal, query: Traversal, radius: str | None = None, file: str | Path | None = None,
    description: str | Path | None = None, whole: bool = False, layout: str | None = None,
) -> GroundTruth:
    """Ground truth from a file, a radius (``25m``, ``2f``), or else the ``[ground_truth]`` table of a description
    file (``dataset.toml``) the reference came from. Both a radius and a file is an error; ``whole`` traversals (no
    ``--frames`` cut) must be the file's size."""
    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.data.sources import ground_truth_spec

    if radius and file:
        raise SettingError(f"give {{radius}} or {{ground_truth}}, not both: {file} decides which frames match")
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
