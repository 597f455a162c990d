"""Scores of predictions against ground truth: Recall@K within a radius, precision-recall, predictions files."""

from seqvpr.evaluation.metrics import Evaluation, PRCurve, evaluate, pr_curve, recall_at_k

__all__ = ["Evaluation", "PRCurve", "evaluate", "pr_curve", "recall_at_k"]
