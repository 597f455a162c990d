"""Compact descriptor stores of a map, decoded as matching reads them: ``sq8`` (8-bit codes over each dimension's
range) and ``pq:M`` (product quantisation: M sub-vectors of D/M dimensions, each one byte naming one of 256
centroids, trained on a seeded sample of the map). Both keep only the codes: re-scoring uses the decoded rows."""

from __future__ import annotations

import re

import numpy as np

from seqvpr.errors import SeqvprError

PLAIN = ("float32", "float16")
SIDE_FILES = {"sq8": "quantizer.npy", "pq": "pq_centroids.npy"}
PQ_TRAIN_ROWS = 65_536  # sample the sub-quantisers are trained on


def parse_storage(storage: str, dim: int | None = None) -> tuple[str, int]:
    """``float32``, ``float16``, ``sq8`` or ``pq:M`` -> (kind, M); M must divide ``dim`` when it is known."""
    if storage in PLAIN or storage == "sq8":
        return storage, 0
    match = re.fullmatch(r"pq:(\d+)", storage)
    if not match or int(match.group(1)) < 1:
        raise SeqvprError(f"map storage {storage!r} is not known (float32, float16, sq8 or pq:M, e.g. pq:64)")
    m = int(match.group(1))
    if dim is not None and dim % m:
        raise SeqvprError(f"--dtype {storage}: M = {m} must divide the dimension {dim}")
    return "pq", m


def stored_shape(storage: str, count: int, dim: int) -> tuple[tuple[int, int], str]:
    """Shape and dtype of ``descriptors.npy`` for a storage."""
    kind, m = parse_storage(storage)
    if kind in PLAIN:
        return (count, dim), kind
    return ((count, m) if kind == "pq" else (count, dim)), "uint8"


class ScalarCodes:
    """``sq8`` rows: uint8 codes (memory-mapped) decoded on access to ``offset + step * code`` per dimension.
    Indexed like an array (slices, row arrays), a chunk at a time."""

    ndim = 2
    dtype = np.dtype(np.float32)

    def __init__(self, codes: np.ndarray, side: np.ndarray) -> None:
        self.codes, self.offset, self.step = codes, side[0].astype(np.float32), side[1].astype(np.float32)
        self.shape = codes.shape

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def nbytes(self) -> int:
        return int(self.codes.nbytes)

    def __getitem__(self, key) -> np.ndarray:
        return self.codes[key].astype(np.float32) * self.step + self.offset


class ProductCodes(ScalarCodes):
    """``pq:M`` rows: uint8 codes [N, M] decoded on access to the concatenated sub-centroids [N, D]."""

    def __init__(self, codes: np.ndarray, side: np.ndarray) -> None:
        self.codes, self.centroids = codes, side.astype(np.float32)  # [M, 256, D / M]
        self.shape = (codes.shape[0], side.shape[0] * side.shape[2])

    def __getitem__(self, key) -> np.ndarray:
        codes = np.asarray(self.codes[key])
        parts = [self.centroids[m][codes[..., m]] for m in range(self.centroids.shape[0])]
        return np.concatenate(parts, axis=-1)


def encode(rows: np.ndarray, storage: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """The stored array of ``rows`` [N, D] and its side array (None for the plain storages)."""
    kind, m = parse_storage(storage, rows.shape[1])
    if kind in PLAIN:
        return np.ascontiguousarray(rows, dtype=kind), None
    if kind == "sq8":
        low, high = rows.min(axis=0), rows.max(axis=0)
        step = np.maximum((high - low) / 255.0, np.finfo(np.float32).tiny).astype(np.float32)
        codes = np.clip(np.rint((rows - low) / step), 0, 255).astype(np.uint8)
        return codes, np.stack([low.astype(np.float32), step])
    return _product_quantize(np.ascontiguousarray(rows, dtype=np.float32), m, seed)


def _product_quantize(rows: np.ndarray, m: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """PQ codes [N, M] and centroids [M, 256, D / M], trained by faiss on a seeded sample of the rows."""
    import faiss

    n, dim = rows.shape
    if n < 256:
        raise SeqvprError(f"--dtype pq:{m} needs at least 256 frames to train its codebooks, the map has {n}")
    quantizer = faiss.ProductQuantizer(dim, m, 8)
    quantizer.cp.seed = seed
    sample = np.sort(np.random.default_rng(seed).choice(n, size=min(n, PQ_TRAIN_ROWS), replace=False))
    quantizer.train(np.ascontiguousarray(rows[sample]))
    codes = np.concatenate([quantizer.compute_codes(rows[b : b + PQ_TRAIN_ROWS]) for b in range(0, n, PQ_TRAIN_ROWS)])
    centroids = faiss.vector_to_array(quantizer.centroids).reshape(m, 256, dim // m)
    return codes.astype(np.uint8), centroids


def decoded_rows(storage: str, stored: np.ndarray, side: np.ndarray | None):
    """The rows matching reads: the stored array itself, or its codes decoded on access."""
    kind, _ = parse_storage(storage)
    if kind in PLAIN:
        return stored
    return ScalarCodes(stored, side) if kind == "sq8" else ProductCodes(stored, side)
