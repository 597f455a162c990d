"""Learnable parts, each owning its model folder (save and load); ``registry`` has one record per model kind.
Never imports ``seqvpr.training``."""
