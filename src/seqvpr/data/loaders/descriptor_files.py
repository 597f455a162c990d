"""Descriptor arrays from .npy, .npz and MATLAB .mat files (dense or scipy-sparse), rows = frames.

A variable is named as ``FILE:VAR``; without it the loader takes the only 2-D numeric array in the file, and
fails naming the candidates when there are several.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from seqvpr.arrays import check_regular_file, load_mat, load_npy, open_npz, release_pages
from seqvpr.errors import SeqvprError

DESCRIPTOR_SUFFIXES = (".npy", ".npz", ".mat")


def split_variable(source: str) -> tuple[Path, str | None]:
    """``path.mat:Y`` -> (path.mat, 'Y'); a plain existing path -> (path, None)."""
    path = Path(source)
    if path.exists() or ":" not in source:
        return path, None
    head, _, var = source.rpartition(":")
    if not var or "/" in var or "\\" in var:
        return path, None
    return Path(head), var


def load_descriptor_array(source: str | Path) -> np.ndarray:
    """A float [N, D] array from a descriptor file (``FILE`` or ``FILE:VAR``), checked for shape and NaN."""
    path, var = split_variable(str(source))
    if not path.exists():
        raise SeqvprError(f"{path}: descriptor file not found")
    check_regular_file(path, "a descriptor file")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        array = _load_npy(path)
    elif suffix == ".npz":
        array = _load_npz(path, var)
    elif suffix == ".mat":
        array = _load_mat(path, var)
    else:
        raise SeqvprError(f"{path}: unknown descriptor format {suffix!r} (expected .npy, .npz or .mat)")
    return _validated(array, f"{path}" + (f":{var}" if var else ""))


def _load_npy(path: Path) -> np.ndarray:
    """The array memory-mapped read-only (a map of ten million rows is read as it is used, never whole)."""
    try:
        return load_npy(path, mmap_mode="r")
    except SeqvprError:
        raise
    except ValueError as error:
        raise SeqvprError(f"{path}: not a numeric .npy array ({error})") from None


def _load_npz(path: Path, var: str | None) -> np.ndarray:
    try:
        with open_npz(path) as archive:
            names = list(archive.files)
            if {"format", "shape", "data", "indices", "indptr"} <= set(names) and var is None:
                return sp.load_npz(path)
            arrays = {name: archive[name] for name in names}
    except SeqvprError:
        raise
    except (ValueError, zipfile.BadZipFile) as error:
        raise SeqvprError(f"{path}: not a readable .npz archive ({error})") from None
    return _pick(arrays, var, path)


def _load_mat(path: Path, var: str | None) -> np.ndarray:
    contents = load_mat(path)
    arrays = {k: v for k, v in contents.items() if not k.startswith("__")}
    return _pick(arrays, var, path)


def _pick(arrays: dict, var: str | None, path: Path):
    """The named variable, or the only 2-D numeric one."""
    if var is not None:
        if var not in arrays:
            raise SeqvprError(f"{path}: no variable {var!r} (found: {', '.join(sorted(arrays)) or 'none'})")
        return arrays[var]
    candidates = [k for k, v in arrays.items() if (sp.issparse(v) or np.asarray(v).ndim == 2) and _numeric(v)]
    if len(candidates) != 1:
        found = ", ".join(sorted(candidates)) or "none"
        raise SeqvprError(f"{path}: name the descriptor variable as {path}:NAME (2-D numeric variables: {found})")
    return arrays[candidates[0]]


def _numeric(value) -> bool:
    dtype = value.dtype if hasattr(value, "dtype") else np.asarray(value).dtype
    return np.issubdtype(dtype, np.number)


#: rows checked at a time
CHECK_ROWS = 1 << 16


def _validated(array, label: str) -> np.ndarray:
    """Dense float array [N, D] without NaN/inf, else a one-line error naming the file and row."""
    if sp.issparse(array):
        array = array.toarray()
    array = np.asarray(array)
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise SeqvprError(f"{label}: descriptors must be real numbers, got {array.dtype}")
    if array.ndim != 2:
        raise SeqvprError(f"{label}: descriptors must be 2-D [frames, dim], got shape {array.shape}")
    if array.shape[0] == 0:
        raise SeqvprError(f"{label}: no descriptor rows (empty traversal)")
    if array.shape[1] == 0:
        raise SeqvprError(f"{label}: descriptors have dimension 0")
    if not np.issubdtype(array.dtype, np.floating):
        array = array.astype(np.float32)
    for start in range(0, len(array), CHECK_ROWS):  # a block at a time: no full-size temporary
        block = array[start : start + CHECK_ROWS]
        bad = ~np.isfinite(block).all(axis=1)
        release_pages(block)  # a memory-mapped file's pages go back as they are checked
        if bad.any():
            raise SeqvprError(f"{label}: row {start + int(np.flatnonzero(bad)[0])} contains NaN or infinity")
    return array
