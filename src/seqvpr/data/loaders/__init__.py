"""Readers for the file formats users have; each returns Traversals and fails with a one-line SeqvprError."""
