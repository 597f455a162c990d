"""Losses, miners, training loops and checkpoints."""
