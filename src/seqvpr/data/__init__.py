"""Traversals, ground truth and the loaders that build them from users' files."""

from seqvpr.data.groundtruth import GroundTruth, Radius, ground_truth_within_radius, parse_radius
from seqvpr.data.traversal import Traversal, segments_from_gaps

__all__ = [
    "GroundTruth",
    "Radius",
    "Traversal",
    "ground_truth_within_radius",
    "parse_radius",
    "segments_from_gaps",
]
