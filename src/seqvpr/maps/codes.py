"""Compact descriptor stores of a map, decoded as matching reads them: ``sq8`` (8-bit codes over each dimension's
range) and ``pq:M`` (product quantisation: M sub-vectors of D/M dimensions, each one byte naming one of 256
centroids, trained on a seeded sample of the map). Both keep only the codes: re-scoring uses the decoded rows."""

from __future__ import annotations

import re

import numpy as np

from seqvpr.errors import SeqvprError, SettingError

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
        raise SettingError(f"{{dtype}} {storage}: M = {m} must divide the dimension {dim}")
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


#: rows read, normalised and encoded at a time when a map is written (peak memory does not grow with the map)
CHUNK_ROWS = PQ_TRAIN_ROWS


def row_chunks(rows, chunk: int | None = None):
    """``(start, float32 block)`` over the rows of any array-like indexed by slices (a memory map, lazy rows),
    ``chunk`` rows at a time (``CHUNK_ROWS`` by default)."""
    chunk = chunk or CHUNK_ROWS
    for start in range(0, len(rows), chunk):
        yield start, np.asarray(rows[start : start + chunk], dtype=np.float32)


def sampled_rows(rows, picked: np.ndarray, chunk: int | None = None) -> np.ndarray:
    """The rows at sorted row numbers ``picked``, read a chunk at a time."""
    chunk = chunk or CHUNK_ROWS
    parts = []
    for start in range(0, len(rows), chunk):
        inside = picked[(picked >= start) & (picked < start + chunk)]
        if len(inside):
            parts.append(np.asarray(rows[start : start + chunk], dtype=np.float32)[inside - start])
    return np.concatenate(parts)


def fit_encoder(rows, storage: str, seed: int = 0):
    """The encoder of ``storage`` fitted to ``rows`` (read a chunk at a time): a function from a float32 block to
    its stored block, and the side array it was fitted with (None for the plain storages). sq8's range is the
    rows' exact minimum and maximum; pq's codebooks are trained on a seeded sample."""
    kind, m = parse_storage(storage, rows.shape[1])
    return _coder(rows, kind, m, seed)


def write_encoded(path, rows, storage: str, seed: int = 0, fitted=None) -> np.ndarray | None:
    """``rows`` [N, D] (read a chunk at a time) stored as ``storage`` into the ``.npy`` at ``path``, written a chunk
    at a time, by ``fitted`` (``fit_encoder``'s, e.g. fitted to a whole map whose shard these rows are) or an encoder
    fitted to them; the side array returned (None for the plain storages). The same bytes as encoding them whole."""
    from numpy.lib import format as npy

    shape, dtype = stored_shape(storage, len(rows), rows.shape[1])
    coder, side = fitted or fit_encoder(rows, storage, seed)
    # plain writes, not a memory map: a full device is an OSError here, where a mapped write would be a SIGBUS
    with open(path, "wb") as handle:
        npy.write_array_header_1_0(handle, {"descr": npy.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
                                            "shape": shape})
        for _, block in row_chunks(rows):
            handle.write(np.ascontiguousarray(coder(block), dtype=dtype).tobytes())
    return side


def _coder(rows, kind: str, m: int, seed: int):
    """The function from a float32 block to its stored block, and the side array it was fitted with."""
    if kind in PLAIN:
        return (lambda block: block.astype(kind)), None
    if kind == "sq8":
        ranges = [(block.min(axis=0), block.max(axis=0)) for _, block in row_chunks(rows)]  # one pass
        low, high = np.min([r[0] for r in ranges], axis=0), np.max([r[1] for r in ranges], axis=0)
        step = np.maximum((high - low) / 255.0, np.finfo(np.float32).tiny).astype(np.float32)
        side = np.stack([low.astype(np.float32), step])
        return coder_of("sq8", side), side
    import faiss

    quantizer = _train_product_quantizer(rows, m, seed)
    centroids = faiss.vector_to_array(quantizer.centroids).reshape(m, 256, rows.shape[1] // m)
    return (lambda block: quantizer.compute_codes(np.ascontiguousarray(block)).astype(np.uint8)), centroids


def coder_of(storage: str, side: np.ndarray | None):
    """The encoder a stored map was written with, from its side array: what encodes rows added to it
    (``seqvpr.maps.grow``) exactly as its own rows were."""
    kind, _ = parse_storage(storage)
    if kind in PLAIN:
        return lambda block: block.astype(kind)
    if kind == "sq8":
        low, step = side[0], side[1]
        return lambda block: np.clip(np.rint((block - low) / step), 0, 255).astype(np.uint8)
    import faiss

    m, _, sub = side.shape
    quantizer = faiss.ProductQuantizer(m * sub, m, 8)
    faiss.copy_array_to_vector(np.ascontiguousarray(side, dtype=np.float32).ravel(), quantizer.centroids)
    return lambda block: quantizer.compute_codes(np.ascontiguousarray(block, dtype=np.float32)).astype(np.uint8)


def _train_product_quantizer(rows, m: int, seed: int):
    """A faiss product quantiser of M sub-vectors, trained on a seeded sample of the rows."""
    import faiss

    n, dim = len(rows), rows.shape[1]
    if n < 256:
        raise SettingError(f"{{dtype}} pq:{m} needs at least 256 frames to train its codebooks, the map has {n}")
    quantizer = faiss.ProductQuantizer(dim, m, 8)
    quantizer.cp.seed = seed
    sample = np.sort(np.random.default_rng(seed).choice(n, size=min(n, PQ_TRAIN_ROWS), replace=False))
    quantizer.train(np.ascontiguousarray(sampled_rows(rows, sample)))
    return quantizer


def decoded_rows(storage: str, stored: np.ndarray, side: np.ndarray | None):
    """The rows matching reads: the stored array itself, or its codes decoded on access."""
    kind, _ = parse_storage(storage)
    if kind in PLAIN:
        return stored
    return ScalarCodes(stored, side) if kind == "sq8" else ProductCodes(stored, side)
