"""Loop closures within a drive (``seqvpr.cli.loops`` is its command): for each frame, causal sequence matching against every earlier frame of the drive
outside an exclusion of the recent past (``seqvpr.data.exclusion``), and, over several sessions, against the
earlier sessions whole. The one matching kernel does it (``sequence_topk`` with per-frame row limits: the triangle
of the drive against itself, never the square); ``seqvpr.localization.loop_detector.LoopDetector`` does the same a
frame at a time, and gives the same matches.

    loops = find_loops(load_drive(["run1.npz", "run2.npz"]), LoopSettings(seq_len=5, exclude="200f"))
    scored = score_loops(loops, "25m")        # correct, true revisits, recall at 100 % precision, PR-AUC
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from seqvpr import checks
from seqvpr.data.exclusion import Exclusion, eligible_limits, parse_exclusion
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.evaluation.metrics import PRCurve, pr_curve
from seqvpr.methods import METHODS, get_method
from seqvpr.progress import ProgressFactory

#: frames excluded before each frame when none is given: seconds where the drive has timestamps, else frames
DEFAULT_SECONDS, DEFAULT_FRAMES = "30s", "100f"


def loop_methods() -> tuple[str, ...]:
    """The methods loop closure runs: those that match frames by constant-velocity sequence windows, which step a
    frame at a time exactly (single-image retrieval is L = 1)."""
    return tuple(name for name, m in METHODS.items() if m.family == "matching" and m.search == "velocity")


@dataclass(frozen=True)
class LoopSettings:
    """How loops are found: ``method`` and ``seq_len`` (causal windows), the recent past excluded (``exclude``:
    ``30s``, ``200f``, ``50m``; None: 30 s with timestamps, else 100 frames), the score's ``exclusion`` (frames
    around the best that are not another place) and the score a loop needs to be accepted (``threshold``; None:
    the method's default). With ``shortlist`` S each frame's candidates are the windows its frames' S nearest
    eligible frames place, found in a ``shortlist_index`` that grows with the drive (``flat`` or ``hnsw:M``), and
    re-ranked exactly: O(N S) for long drives instead of the exhaustive triangle (0)."""

    method: str = "matching"
    seq_len: int = 5
    exclude: str | Exclusion | None = None
    exclusion: int = 10
    threshold: float | None = None
    shortlist: int = 0
    shortlist_index: str = "hnsw:32"

    def __post_init__(self) -> None:
        methods = loop_methods()
        if checks.text(self.method, "method") not in methods:
            get_method(self.method)  # an unknown name: one line listing the methods
            raise SettingError(f"loop closure runs {', '.join(methods)}, not {{method}} {self.method}")
        object.__setattr__(self, "seq_len", checks.whole(self.seq_len, "seq_len", 1))
        object.__setattr__(self, "exclusion", checks.whole(self.exclusion, "exclusion", 0))
        if self.exclude is not None:
            object.__setattr__(self, "exclude", parse_exclusion(self.exclude))
        if self.threshold is not None:
            object.__setattr__(self, "threshold", checks.finite(self.threshold, "threshold"))
        object.__setattr__(self, "shortlist", checks.whole(self.shortlist, "shortlist", 0))
        if self.shortlist:
            from seqvpr.localization.loop_shortlist import check_shortlist_index

            check_shortlist_index(checks.text(self.shortlist_index, "shortlist_index"))

    @property
    def window(self) -> int:
        """Frames a window spans: the method's own length (1 for ``single``), else ``seq_len``."""
        return get_method(self.method).length or self.seq_len

    @property
    def accept(self) -> float:
        """The score a loop needs."""
        return self.threshold if self.threshold is not None else get_method(self.method).threshold

    def exclusion_for(self, drive: Traversal) -> Exclusion:
        """The exclusion given, else the default for this drive."""
        if isinstance(self.exclude, Exclusion):
            return self.exclude
        return parse_exclusion(DEFAULT_SECONDS if drive.timestamps is not None else DEFAULT_FRAMES)

    def ranked(self) -> int:
        """How many best windows a frame keeps: enough for the score's best other place."""
        return 2 * self.exclusion + 2


@dataclass(frozen=True)
class Drive:
    """One or more traversals laid end to end as sessions (each its own segments): ``sessions`` [N] the session of
    each row, ``session_names`` their names."""

    frames: Traversal
    sessions: np.ndarray
    session_names: tuple[str, ...]


@dataclass(frozen=True)
class Loops:
    """For each frame of a drive: its eligible rows ``[0, limits[i])``, the best earlier frame (``match``, -1 when
    none is eligible or no window exists), its sequence ``distance``, the ``score`` (uniqueness, as the localiser
    scores) and whether it is ``accepted``."""

    drive: Drive
    settings: LoopSettings
    exclusion: Exclusion
    limits: np.ndarray
    match: np.ndarray
    distance: np.ndarray
    score: np.ndarray
    accepted: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class ScoredLoops:
    """Loops against ground truth: ``correct`` (the match is within the radius), ``revisit`` (some eligible frame
    is: the frame is a true loop), and the precision-recall curve over the score threshold."""

    correct: np.ndarray
    revisit: np.ndarray
    pr: PRCurve
    radius: str


def make_drive(traversals: Sequence[Traversal], names: Sequence[str] | None = None) -> Drive:
    """Traversals as sessions of one drive, in time order where every one has timestamps (as given otherwise)."""
    from seqvpr.maps.build import concatenate_traversals

    if not traversals:
        raise SeqvprError("loop closure needs at least one traversal")
    names = list(names or [t.source or t.name for t in traversals])
    order = list(range(len(traversals)))
    if all(t.timestamps is not None for t in traversals):
        order.sort(key=lambda i: float(traversals[i].timestamps[0]))
    ordered = [traversals[i] for i in order]
    sessions = np.repeat(np.arange(len(ordered)), [len(t) for t in ordered])
    frames = concatenate_traversals(ordered, "drive") if len(ordered) > 1 else ordered[0]
    return Drive(frames, sessions, tuple(names[i] for i in order))


def load_drive(sources: Sequence[str], description: Any = None, models: Mapping[str, Any] | None = None, *,
               frames: str | None = None, device: str = "cpu", progress: ProgressFactory | None = None,
               **extraction: Any) -> Drive:
    """Each source read (cut to source frames ``START:STOP`` when given) and described as a map's frames are
    (``maps.build.describe_frames``: descriptor files as they are, images through ``description`` or an image
    model among ``models``), as the sessions of one drive."""
    from seqvpr.data.sources import load_traversal
    from seqvpr.data.traversal import slice_frame_range
    from seqvpr.maps.build import FrameDescription, describe_frames, with_default_cache

    description = description or FrameDescription()
    extraction = with_default_cache(description, dict(models or {}), extraction)
    parts = [describe_frames(slice_frame_range(load_traversal(source, "query"), frames), description,
                             dict(models or {}), device, progress, **extraction) for source in sources]
    return make_drive(parts, [str(source) for source in sources])


def loop_limits(drive: Drive, exclusion: Exclusion) -> np.ndarray:
    """Each frame's eligible rows ``[0, limit)``."""
    frames = drive.frames
    return eligible_limits(exclusion, drive.sessions, frames.timestamps, frames.positions,
                           frames.source or frames.name)


def find_loops(drive: Drive, settings: LoopSettings = LoopSettings(), models: Mapping[str, Any] | None = None, *,
               memory_budget: int | None = None, progress: ProgressFactory | None = None) -> Loops:
    """Every frame's best earlier frame outside the exclusion, by causal sequence matching in one blocked pass over
    the triangle (or, with the settings' ``shortlist``, among the windows a growing frame index places);
    ``models`` may hold a SeqMatchNet transform (``seqmatchnet``)."""
    from seqvpr.sequences.match_settings import DEFAULT_BUDGET
    from seqvpr.sequences.matching import sequence_topk

    from seqvpr.sequences.windows import check_length

    rows, segments = loop_rows(drive, settings, models)
    check_length(settings.window, segments, drive.frames.source or drive.frames.name)
    exclusion = settings.exclusion_for(drive.frames)
    limits = loop_limits(drive, exclusion)
    tick = progress(len(rows), "loops") if progress else None
    if settings.shortlist:
        from seqvpr.localization.loop_shortlist import shortlisted_topk

        top = shortlisted_topk(rows, segments, causal_spec(settings), settings.ranked(), limits, settings.shortlist,
                               settings.shortlist_index, tick)
        return loops_from(drive, settings, exclusion, limits, top.indices, top.distances)
    top = sequence_topk(rows, rows, causal_spec(settings), settings.ranked(), segments, segments,
                        memory_budget=memory_budget or DEFAULT_BUDGET, progress=tick, limits=limits)
    return loops_from(drive, settings, exclusion, limits, top.indices, top.distances)


def causal_spec(settings: LoopSettings):
    """Causal windows of the settings' length, dropped where they would cross a segment."""
    from seqvpr.sequences.windows import SequenceSpec

    return SequenceSpec(settings.window, "causal", "drop")


def loop_rows(drive: Drive, settings: LoopSettings, models: Mapping[str, Any] | None):
    """The drive's rows as matching reads them (through a SeqMatchNet transform when given; unit length), and its
    segments."""
    from seqvpr.matchers.rows import query_rows, transformed_by
    from seqvpr.sequences.match_settings import MatchSettings

    frames = transformed_by(drive.frames, dict(models or {}))
    if frames.descriptors is None:
        raise SeqvprError(f"{frames.source or frames.name}: no descriptors (describe the images first)")
    return query_rows(frames, MatchSettings()), np.asarray(drive.frames.segment_ids)


def loops_from(drive: Drive, settings: LoopSettings, exclusion: Exclusion, limits: np.ndarray,
               indices: np.ndarray, distances: np.ndarray) -> Loops:
    """Loops from each frame's ranked earlier windows [N, K] (best first; -1 / +inf empty)."""
    score = np.array([loop_score(i, d, settings.exclusion) for i, d in zip(indices, distances)])
    match = np.where(np.isfinite(distances[:, 0]), indices[:, 0], -1)
    distance = np.where(match >= 0, distances[:, 0], np.inf)
    score = np.where(match >= 0, score, 0.0)
    return Loops(drive, settings, exclusion, limits, match, distance, score, (match >= 0) & (score >= settings.accept))


def loop_score(indices: np.ndarray, distances: np.ndarray, exclusion: int) -> float:
    """The localiser's uniqueness (``uniqueness_ratio``) of one frame's ranked earlier windows, but 0 where no other
    place is eligible at all: early in a drive a frame's few candidates all lie near one another, and a match with
    no rival is not a sure one."""
    from seqvpr.sequences.topk import other_place, uniqueness_ratio

    if other_place(indices, distances, exclusion)[0] < 0 and np.isfinite(distances).sum() < 2 * exclusion + 2:
        return 0.0
    return uniqueness_ratio(indices, distances, exclusion)


def score_loops(loops: Loops, radius: str, ground_truth=None) -> ScoredLoops:
    """Which matches are right (within ``radius`` of the frame: ``25m`` or ``2f``) and which frames truly revisit
    an eligible frame; the PR curve over the score (higher accepts first), frames with no true revisit counting
    as false positives when they are accepted."""
    from seqvpr.data.ground_truth import ground_truth_within_radius, parse_radius

    frames = loops.drive.frames
    gt = ground_truth or ground_truth_within_radius(frames, frames, parse_radius(radius))
    correct = gt.contains(np.arange(len(frames)), loops.match)
    revisit = eligible_positive(gt.positives, loops.limits)
    # the PR curve ranks by distance (lower accepted first): a higher score is a lower -score
    candidates = np.where(loops.match >= 0, -loops.score, np.inf)
    return ScoredLoops(correct, revisit, pr_curve(candidates, correct, int(revisit.sum())), str(radius))


def eligible_positive(positives, limits: np.ndarray) -> np.ndarray:
    """Per frame, whether any of its positives (CSR rows) lies before its limit."""
    indptr, indices = positives.indptr, positives.indices
    first = np.full(len(limits), np.iinfo(np.int64).max)
    has = np.diff(indptr) > 0
    first[has] = indices[indptr[:-1][has]]  # sorted indices: a row's first positive is its smallest
    return first < limits


def loops(
    sources: Sequence[str] | str,
    *,
    method: str = "matching",
    seq_len: int = 5,
    exclude: str | None = None,
    exclusion: int = 10,
    threshold: float | None = None,
    shortlist: int = 0,
    shortlist_index: str = "hnsw:32",
    radius: str | None = None,
    models: Any = None,
    description: Any = None,
    frames: str | None = None,
    memory_budget: int | None = None,
    progress: ProgressFactory | None = None,
    **extraction: Any,
):
    """Loop closures over one drive, or several as sessions in time order (``seqvpr.localization.loops``): each
    frame's best earlier frame outside ``exclude`` (``30s``, ``200f``, ``50m``) by causal sequence matching, its
    score and acceptance, and, with ``radius`` (``25m``, ``2f``), which are right with the PR curve over the score.
    With ``shortlist`` S, each frame's candidates come from a frame index that grows with the drive
    (``shortlist_index``: ``hnsw:M`` or ``flat``), O(N S). Returns (``Loops``, ``ScoredLoops`` or None)."""
    from seqvpr.api import load_models
    from seqvpr.features.describe import check_extraction_settings

    from seqvpr.data.ground_truth import parse_radius
    from seqvpr.methods import check_run

    # checked before anything is read
    settings = LoopSettings(method, seq_len, exclude, exclusion, threshold, shortlist, shortlist_index)
    listed = checks.paths(sources, "sources")
    unit = None if radius is None else parse_radius(checks.text(radius, "radius")).unit
    check_extraction_settings(**extraction)
    loaded = load_models(models)
    check_run(method, loaded)
    drive = load_drive(listed, description, loaded, frames=frames, progress=progress, **extraction)
    if unit == "m" and drive.frames.positions is None:
        raise SettingError(f"{drive.frames.source or drive.frames.name}: {{radius}} {radius} is in metres but the "
                           "drive has no positions (use frames, e.g. 2f)")
    found = find_loops(drive, settings, loaded, memory_budget=memory_budget, progress=progress)
    return found, (score_loops(found, radius) if radius is not None else None)
