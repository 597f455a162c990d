"""Scores of predictions against ground truth: Recall@K within a radius, precision-recall, predictions files,
the HTML report."""
