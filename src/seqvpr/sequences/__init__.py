"""Sequence windows, the matching kernel, sequence descriptors, retrieval and hierarchical re-ranking."""
