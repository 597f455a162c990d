"""What a run reports: the recall table as text, and the evaluation as a JSON-ready dict (``run.json``)."""

from __future__ import annotations

from collections.abc import Sequence

from seqvpr.evaluation.metrics import Evaluation


def recall_table(evaluation: Evaluation, label: str, width: int = 14) -> str:
    """A small text table: one row with R@K for each K, AUC and R@100P, and the query counts."""
    return recall_rows([(label, evaluation)], width)


def recall_rows(rows: Sequence[tuple[str, Evaluation]], width: int = 14) -> str:
    """One row per (label, evaluation) under one header, then the first evaluation's query counts; the label
    column widens to the longest label (never cut)."""
    width = max(width, *(len(label) + 2 for label, _ in rows))
    ks = list(rows[0][1].recall)
    header = f"{'':<{width}}" + "".join(f"{'R@' + str(k):>8}" for k in ks) + f"{'PR-AUC':>8}{'R@100P':>8}"
    lines = [recall_row(evaluation, label, width) for label, evaluation in rows]
    return "\n".join([header, *lines, query_counts(rows[0][1])])


def recall_row(evaluation: Evaluation, label: str, width: int = 14) -> str:
    """The table's row: the label, R@K for each K, AUC and R@100P."""
    row = f"{label:<{width}}" + "".join(f"{value:>8.3f}" for value in evaluation.recall.values())
    return row + f"{evaluation.pr.auc:>8.3f}{evaluation.pr.recall_at_100_precision:>8.3f}"


def query_counts(evaluation: Evaluation) -> str:
    """How many queries were scored and why the others were not."""
    return (
        f"queries evaluated: {evaluation.queries_evaluated}; excluded: {evaluation.queries_excluded} "
        f"(no window: {evaluation.excluded_no_window}, no positive: {evaluation.excluded_no_positive}, "
        f"policy: {evaluation.no_positive})"
    )


def json_number(value: float) -> float | None:
    """A float as strict JSON takes it: NaN and infinities become null."""
    import math

    return float(value) if value is not None and math.isfinite(value) else None


def evaluation_json(evaluation: Evaluation, settings: dict) -> dict:
    """Recall@K, PR-AUC, R@100P, the query counts and the run's ``settings``, as JSON-ready values (a figure that
    cannot be computed, with no query scored, is null: strict JSON has no NaN)."""
    return {
        "recall": {str(k): json_number(v) for k, v in evaluation.recall.items()},
        "pr_auc": json_number(evaluation.pr.auc),
        "recall_at_100_precision": json_number(evaluation.pr.recall_at_100_precision),
        "frame_precision": json_number(evaluation.frame_precision),
        "queries_evaluated": evaluation.queries_evaluated,
        "queries_excluded": evaluation.queries_excluded,
        "excluded_no_window": evaluation.excluded_no_window,
        "excluded_no_positive": evaluation.excluded_no_positive,
        "settings": settings,
    }
