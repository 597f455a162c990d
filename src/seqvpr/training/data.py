"""The one place that turns a radius and train/validation pairs into a model kind's ``TrainingData``: the
negative-radius default of each kind, and JIST's positions for frame-aligned images. ``seqvpr train`` and
``seqvpr benchmark`` both call it, so their defaults cannot disagree."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from seqvpr.data.ground_truth import Radius
from seqvpr.data.sources import load_pair, load_traversal
from seqvpr.data.traversal import Traversal, check_disjoint, slice_frame_range
from seqvpr.errors import SettingError
from seqvpr.training.settings import NEGATIVE_RADIUS_FACTOR
from seqvpr.training.trainer import TrainingData


Pair = tuple[Traversal, Traversal]


def training_radii(
    kind: str, radius: Radius, positive: Radius | None = None, negative: Radius | None = None
) -> tuple[Radius, Radius, Radius]:
    """Validation radius, positive radius (default: the validation one) and negative radius (default: the kind's
    factor times the positive one)."""
    positive = positive or radius
    negative = negative or Radius(NEGATIVE_RADIUS_FACTOR[kind] * positive.value, positive.unit)
    if kind == "jist" and len({radius.unit, positive.unit, negative.unit}) > 1:
        raise SettingError("{radius}, {pos_radius} and {neg_radius} must share one unit (all m or all f)")
    return radius, positive, negative


def training_data(
    kind: str, train: Pair, validation: Pair, radius: Radius, positive: Radius | None = None,
    negative: Radius | None = None,
) -> TrainingData:
    """The ``TrainingData`` of ``kind`` (``seqmatchnet``, ``seqnet``, ``jist``) with its radius defaults; JIST's
    frame-aligned images get along-route positions (``jist_positions``) so CosPlace cells count frames."""
    val, pos, neg = training_radii(kind, radius, positive, negative)
    if kind == "jist":
        from seqvpr.training.jist import jist_positions

        train = tuple(jist_positions(t, val) for t in train)  # type: ignore[assignment]
        validation = tuple(jist_positions(t, val) for t in validation)  # type: ignore[assignment]
    return TrainingData(*train, *validation, pos, neg, val)


def training_pairs(
    reference: str,
    query: str,
    train_frames: str,
    val_frames: str,
    prepare: Callable[[Traversal, Traversal], Pair],
    *,
    frames: str | None = None,
    val_reference: str | None = None,
    val_query: str | None = None,
) -> tuple[Pair, Pair, Pair]:
    """The train and validation pairs: the sources loaded (``frames`` kept), passed through ``prepare`` (e.g.
    described) and cut to ``train_frames`` / ``val_frames``; validation comes from other sources when given, and
    must not overlap training when it does not. Returns them with the whole prepared training pair."""
    whole = prepare(*load_pair(reference, query, frames))
    if val_reference or val_query:
        val_whole = prepare(*load_pair(val_reference or reference, val_query or query, frames))
    else:
        check_disjoint(train_frames, val_frames, ("--train-frames", "--val-frames"))
        val_whole = whole
    train = tuple(slice_frame_range(t, train_frames, "--train-frames") for t in whole)
    validation = tuple(slice_frame_range(t, val_frames, "--val-frames") for t in val_whole)
    return train, validation, whole  # type: ignore[return-value]


def classification_traversals(
    data: TrainingData, sources: Sequence[str], train_frames: str, frames: str | None = None
) -> tuple[Traversal, ...] | None:
    """JIST's classification traversals: the training pair plus the ``train_frames`` of other traversals of the
    same route (more conditions of each place), placed as the pair is (``jist_positions``); None without others
    (the learner's default, the pair)."""
    if not sources:
        return None
    from seqvpr.training.jist import jist_positions

    extra = [slice_frame_range(slice_frame_range(load_traversal(s, "query"), frames), train_frames, "--train-frames")
             for s in sources]
    return (data.reference, data.query, *(jist_positions(t, data.val_radius) for t in extra))
