"""Traversals, ground truth and the loaders that build them from users' files."""
