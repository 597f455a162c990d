"""Sequence windows, the matching kernel, and (later) sequence descriptors."""
