"""Learnable parts: small torch modules that take descriptors and return descriptors."""
