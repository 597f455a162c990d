"""A map's faiss index over its frames: built once (``--index flat | hnsw:M | ivf:NLIST[,pq:M]``), saved beside the
descriptors as ``index.faiss`` and opened memory-mapped; its searches give the candidate frames that shortlisted
matching re-ranks by exact sequence distance."""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.arrays import load_npy
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.identity import check_digest, remember_digest, seal_files
from seqvpr.io import commit_folder, output_lock, temporary_folder
from seqvpr.maps.files import INFO_FILE, SavedMap, is_plain_name, open_map
from seqvpr.maps.keep import keep_users_files

INDEX_FILE = "index.faiss"
ADD_BLOCK = 65_536  # map rows added to an index at a time (a memory-mapped map is never read whole)
TRAIN_PER_LIST = 64  # training rows per IVF list (faiss asks for at least 39)
DEFAULT_NPROBE = 16
DEFAULT_EF_SEARCH = 64
MAX_HNSW_M = 256  # links an HNSW node keeps: memory grows with M a frame, and faiss fails below 2
PQ_CENTROIDS = 256  # codes of one PQ byte: its k-means needs at least this many training frames


@dataclass(frozen=True)
class IndexSpec:
    """What ``--index`` names: ``flat`` (exact), ``hnsw:M`` (graph, M links a node), ``ivf:NLIST[,pq:M]``
    (NLIST k-means lists, raw vectors or M-byte PQ codes) or ``auto`` (chosen for the map's size)."""

    kind: str
    m: int = 0
    nlist: int = 0
    pq: int = 0

    def __str__(self) -> str:
        if self.kind == "auto":
            return "auto"
        if self.kind == "hnsw":
            return f"hnsw:{self.m}"
        if self.kind == "ivf":
            return f"ivf:{self.nlist}" + (f",pq:{self.pq}" if self.pq else "")
        return "flat"


def parse_index_spec(text: str) -> IndexSpec:
    """``flat``, ``hnsw:32``, ``ivf:1024``, ``ivf:1024,pq:32`` or ``auto`` (``auto_index_spec``); anything else is
    a one-line error."""
    spec = text.strip().lower()
    if spec in ("flat", "auto"):
        return IndexSpec(spec)
    if match := re.fullmatch(r"hnsw:(\d+)", spec):
        if not 2 <= int(match.group(1)) <= MAX_HNSW_M:
            raise SettingError(f"{{index}} {text!r}: hnsw:M needs M at least 2 and at most {MAX_HNSW_M} (links a node)")
        return IndexSpec("hnsw", m=int(match.group(1)))
    if match := re.fullmatch(r"ivf:(\d+)(?:,pq:(\d+))?", spec):
        return IndexSpec("ivf", nlist=_positive(match.group(1), text), pq=_positive(match.group(2) or "0", text, 0))
    raise SettingError(f"{{index}} {text!r}: expected auto, flat, hnsw:M or ivf:NLIST[,pq:M] (e.g. ivf:1024,pq:32)")


def _positive(value: str, text: str, least: int = 1) -> int:
    if int(value) < least:
        raise SettingError(f"{{index}} {text!r}: numbers must be at least {least}")
    return int(value)


#: the sequence descriptors an index over windows can hold (one vector per window; seqnet with its model)
WINDOW_METHODS = ("smoothing", "delta", "seqgem", "seqnet")
ROWS_FILE = "index_rows.npy"


def window_vectors(descriptors, segments: np.ndarray, length: int, method: str, model=None):
    """The ``method`` sequence descriptors of every frame with a centred window of ``length`` frames (the vectors
    ``seqvpr match --method`` retrieves with; ``seqnet`` through ``model``), read from the map a batch at a time."""
    from seqvpr.sequences.descriptors import sequence_descriptors
    from seqvpr.sequences.windows import SequenceSpec

    if method not in WINDOW_METHODS:
        raise SettingError(f"{{window_method}} {method!r} is not known (choose from: {', '.join(WINDOW_METHODS)})")
    rows = descriptors if isinstance(descriptors, np.ndarray) else descriptors[:]  # coded rows: decoded
    return sequence_descriptors(rows, np.asarray(segments), SequenceSpec(length), method, model)


def model_record(folder: str | Path) -> dict[str, str]:
    """The folder and weights' sha256 of a model (what a map or an index over windows was built with): its
    identity, compared by content, never by kind or shape (remembered per file, so a second look costs a stat)."""
    from seqvpr.identity import file_digest
    from seqvpr.models.files import MODEL_FILE

    return {"folder": str(folder), "sha256": file_digest(Path(folder) / MODEL_FILE).split(":", 1)[1]}


def index_model(saved: SavedMap):
    """The SeqNet an index over seqnet windows was built with, loaded from its recorded folder and checked against
    its recorded sha256 (None for the other indexes)."""
    from seqvpr.models.registry import load_trained_model

    record = (saved.info.index or {}).get("model")
    if not record:
        return None
    if not Path(record["folder"]).is_dir() or model_record(record["folder"])["sha256"] != record["sha256"]:
        raise SeqvprError(f"{saved.folder}'s index was built with the SeqNet {record['folder']} "
                          f"(sha256 {record['sha256'][:12]}), which is gone or has changed: rebuild the index")
    return load_trained_model(record["folder"]).module


AUTO_FLAT_BELOW = 10_000  # frames: below this ``auto`` is exact (a copy of a small map costs little)
AUTO_MAX_LISTS = 1024  # IVF lists ``auto`` uses at most: k-means and list assignment stay minutes on two cores
CHECKPOINT_ROWS = 1 << 20  # rows added between two saved partial indexes (``map index`` resumes from the last)


def auto_index_spec(n: int, dim: int) -> IndexSpec:
    """The index ``auto`` builds over ``n`` vectors of ``dim``: ``flat`` for small maps, else IVF-PQ that never
    stores the vectors again (the map's rows serve re-ranking): about sqrt(n) lists (a power of two, 16 to
    ``AUTO_MAX_LISTS``) and PQ codes of one byte for every 8 dimensions (M the largest divisor of ``dim`` up to
    ``dim / 8``)."""
    if n < AUTO_FLAT_BELOW:
        return IndexSpec("flat")
    lists = int(np.clip(2 ** round(np.log2(np.sqrt(n))), 16, AUTO_MAX_LISTS))
    m = max(d for d in range(1, max(1, dim // 8) + 1) if dim % d == 0)
    return IndexSpec("ivf", nlist=lists, pq=m)


def resolved_spec(spec: IndexSpec, n: int, dim: int) -> IndexSpec:
    """``spec`` itself, or what ``auto`` means for ``n`` vectors of ``dim``."""
    return auto_index_spec(n, dim) if spec.kind == "auto" else spec


def build_frame_index(descriptors: np.ndarray, spec: IndexSpec, seed: int = 0, progress=None,
                      partial: Path | None = None, key: dict[str, Any] | None = None):
    """A faiss index over the rows of ``descriptors`` (read a block at a time); IVF lists are trained on a seeded
    sample of ``TRAIN_PER_LIST`` rows a list. With a ``partial`` folder, the index is saved there once trained and
    every ``CHECKPOINT_ROWS`` rows, under ``key`` (what it is built over and how), and a build interrupted with the
    same key goes on from its last save: the same index as one uninterrupted build (rows are added in order)."""
    n, dim = descriptors.shape
    spec = resolved_spec(spec, n, dim)
    check_index_spec(spec, n, dim)
    key = {**(key or {}), "spec": str(spec), "seed": seed, "count": int(n), "dim": int(dim)}
    index, done = resumed_index(partial, key) if partial is not None else (None, 0)
    if index is None:
        index = empty_index(spec, dim)
        if spec.kind == "ivf":
            train = progress(1, f"train {spec} on {min(n, TRAIN_PER_LIST * spec.nlist)} rows") if progress else None
            index.cp.seed = seed
            rows = np.sort(np.random.default_rng(seed).choice(n, size=min(n, TRAIN_PER_LIST * spec.nlist),
                                                              replace=False))
            index.train(np.ascontiguousarray(descriptors[rows], dtype=np.float32))
            if train:
                train(1)
            save_partial(partial, index, 0, key)
    tick = progress(n, f"index {spec}" + (f" (resumed at row {done})" if done else "")) if progress else None
    if tick and done:
        tick(done)
    for begin in range(done, n, ADD_BLOCK):
        index.add(np.ascontiguousarray(descriptors[begin : begin + ADD_BLOCK], dtype=np.float32))
        if tick:
            tick(min(ADD_BLOCK, n - begin))
        added = min(begin + ADD_BLOCK, n)
        if added < n and added % CHECKPOINT_ROWS < ADD_BLOCK:
            save_partial(partial, index, added, key)
    return index


PROGRESS_FILE = "progress.json"


def save_partial(folder: Path | None, index, rows: int, key: dict[str, Any]) -> None:
    """Save a partial index (``rows`` added) to ``folder``: the index under a new name, then ``progress.json``
    naming it (atomically), then the older one removed, so the folder always names a whole file."""
    import faiss

    from seqvpr.io import atomic_write

    if folder is None:
        return
    folder.mkdir(parents=True, exist_ok=True)
    name = f"index-{rows}.faiss"
    faiss.write_index(index, str(folder / f"{name}.part"))
    os.replace(folder / f"{name}.part", folder / name)
    with atomic_write(folder / PROGRESS_FILE) as handle:
        handle.write(json.dumps({"key": key, "rows": rows, "file": name}))
    for old in folder.glob("index-*.faiss"):
        if old.name != name:
            old.unlink(missing_ok=True)


def resumed_index(folder: Path, key: dict[str, Any]):
    """The partial index saved in ``folder`` for ``key`` and the rows it holds, or (None, 0): none saved, saved for
    another map, spec or seed (then cleared), or unreadable."""
    import faiss

    try:
        progress = json.loads((folder / PROGRESS_FILE).read_text())
        if progress["key"] != key or not is_plain_name(progress["file"]):
            raise ValueError("another build")
        index = faiss.read_index(str(folder / progress["file"]))
        if index.ntotal != int(progress["rows"]):
            raise ValueError("rows")
        return index, int(progress["rows"])
    except (OSError, ValueError, KeyError, TypeError, RuntimeError):
        shutil.rmtree(folder, ignore_errors=True)
        return None, 0


def partial_folder(saved: SavedMap) -> Path | None:
    """Where an index of ``saved`` is kept while it is built: beside the map folder, named by the map's identity
    (so a map rebuilt to the same rows, even under a temporary name, finds it), removed once the index is committed;
    None for a map without an identity (its index is not resumable)."""
    if not saved.info.identity:
        return None
    return Path(saved.folder).parent / f".seqvpr-index-{saved.info.identity.split(':')[-1][:16]}"


def check_index_spec(spec: IndexSpec, n: int, dim: int) -> None:
    """One line, before any training, when ``spec`` does not fit ``n`` vectors of ``dim``: more IVF lists than
    vectors, PQ bytes that do not divide the dimension, or fewer vectors than PQ's k-means needs."""
    if spec.kind == "ivf" and spec.nlist > n:
        raise SettingError(f"{{index}} {spec}: {spec.nlist} lists for {n} frames (use at most one list per frame)")
    if spec.pq and dim % spec.pq:
        raise SettingError(f"{{index}} {spec}: pq:{spec.pq} must divide the dimension {dim}")
    if spec.pq and n < PQ_CENTROIDS:
        raise SettingError(f"{{index}} {spec}: PQ trains {PQ_CENTROIDS} codes a byte and needs at least {PQ_CENTROIDS} "
                          f"frames; the map has {n} (use ivf:NLIST without pq)")


def empty_index(spec: IndexSpec, dim: int):
    """An empty faiss index of ``spec`` (IVF still to be trained)."""
    import faiss

    if spec.kind == "flat":
        return faiss.IndexFlatL2(dim)
    if spec.kind == "hnsw":
        index = faiss.IndexHNSWFlat(dim, spec.m)
        index.hnsw.efSearch = DEFAULT_EF_SEARCH
        return index
    quantizer = faiss.IndexFlatL2(dim)
    if spec.pq:
        return faiss.IndexIVFPQ(quantizer, dim, spec.nlist, spec.pq, 8)
    return faiss.IndexIVFFlat(quantizer, dim, spec.nlist)


def add_index(
    saved: SavedMap, spec: IndexSpec, seed: int = 0, progress=None, windows: int = 0, method: str = "smoothing",
    model_folder: str | Path | None = None,
) -> dict[str, Any]:
    """Build the map's index, over its frames or (``windows`` L) over the ``method`` sequence descriptors of its
    windows of L frames, and commit it with the map as one: holding the map's lock, a new version of the map folder
    (its files hard-linked) gains ``index.faiss`` (and, over windows, ``index_rows.npy``, the map row of each vector)
    and ``map.json`` naming them, with their digests and the identity of the rows they index, then replaces the
    map by one atomic exchange. A reader sees the map with its old index or with the new one, never a mix."""
    if windows < 0:
        raise SettingError(f"{{windows}} must be 0 (frames) or a window length, got {windows}")
    if (method == "seqnet") != (model_folder is not None) and windows:
        raise SettingError("an index over seqnet windows needs its SeqNet ({index_model}), and only it takes one")
    with output_lock(saved.folder):
        current = open_map(saved.folder)  # under the lock: the rows this index is built over
        if current.info.identity != saved.info.identity:
            raise SeqvprError(f"{saved.folder}: the map was rebuilt since it was opened; index it again")
        return _index_new_version(current, spec, seed, progress, windows, method, model_folder)


def _index_new_version(saved: SavedMap, spec: IndexSpec, seed: int, progress, windows: int, method: str,
                       model_folder: str | Path | None) -> dict[str, Any]:
    """``add_index``'s work: the index built, written with the map's linked files into a temporary folder, and the
    folder swapped in for the map."""
    import faiss

    started = time.perf_counter()
    model = _seqnet(model_folder) if windows and model_folder is not None else None
    described = window_vectors(saved.descriptors, saved.frames.segment_ids, windows, method, model) if windows else None
    vectors = described.vectors if described else saved.descriptors
    over = f"{method}:{windows}" if windows else "frames"
    partial = partial_folder(saved)
    index = build_frame_index(vectors, spec, seed, progress, partial, {"map": saved.info.identity, "over": over})
    spec = resolved_spec(spec, *vectors.shape)
    record = {"spec": str(spec), "over": over, "file": INDEX_FILE,
              "ntotal": int(index.ntotal), "dim": int(vectors.shape[1]), "seed": seed,
              "build_seconds": round(time.perf_counter() - started, 2), "map": saved.info.identity}
    if model is not None:
        record["model"] = model_record(model_folder)
    folder = Path(saved.folder)
    tmp = temporary_folder(folder)
    try:
        linked = link_map_files(saved, tmp)
        faiss.write_index(index, str(tmp / INDEX_FILE))
        record["digest"] = seal_files(tmp, [INDEX_FILE])[INDEX_FILE]
        if described is not None:
            np.save(tmp / ROWS_FILE, described.rows)
            record.update(rows_file=ROWS_FILE, rows_digest=seal_files(tmp, [ROWS_FILE])[ROWS_FILE])
        (tmp / INFO_FILE).write_text(json.dumps({**saved.info.to_json(), "index": record}, indent=2))
        keep_users_files(folder, tmp)  # a calibration (an index leaves the map's identity as it is), a user's files
        commit_folder(tmp, folder, INFO_FILE)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if partial is not None:
        shutil.rmtree(partial, ignore_errors=True)  # committed: nothing left to resume
    for name, digest in linked.items():  # removing the old links changed the files' change time, not their bytes
        remember_digest(folder / name, digest)
    return record


def link_map_files(saved: SavedMap, folder: Path) -> dict[str, str]:
    """The map's row files (``map.json``'s ``files``) in ``folder``, hard-linked (copied where links are refused),
    each checked against its digest as it is linked; the digests, for the files whose bytes were proven."""
    names = list(saved.info.files or {}) or [p.name for p in Path(saved.folder).iterdir()
                                             if p.is_file() and p.name not in (INFO_FILE, INDEX_FILE, ROWS_FILE)]
    for name in names:
        try:
            os.link(Path(saved.folder) / name, folder / name)
        except OSError:
            shutil.copy2(Path(saved.folder) / name, folder / name)
    proven = {}
    for name, digest in (saved.info.files or {}).items():
        check_digest(folder / name, digest, str(Path(saved.folder) / INFO_FILE))
        proven[name] = digest
    return proven


def open_frame_index(saved: SavedMap, nprobe: int = DEFAULT_NPROBE, ef_search: int = DEFAULT_EF_SEARCH):
    """The map's saved frame index, memory-mapped where faiss can; a map without one is a one-line error."""
    import faiss

    record = saved.info.index
    if not record:
        raise SeqvprError(f"{saved.folder} has no index: add one with seqvpr map index {saved.folder} --index SPEC")
    path = Path(saved.folder) / record["file"]
    if not path.is_file():
        raise SeqvprError(f"{path}: missing map file (map.json names an index)")
    check_index_record(saved, record, path)
    try:
        index = faiss.read_index(str(path), faiss.IO_FLAG_MMAP | faiss.IO_FLAG_READ_ONLY)
    except RuntimeError as error:
        raise SeqvprError(f"{path}: unreadable faiss index ({str(error).splitlines()[0][:120]})") from None
    count = saved.info.count if record["over"] == "frames" else len(indexed_rows(saved))
    dim = record.get("dim", saved.info.dim)
    if index.ntotal != count or index.d != dim:
        raise SeqvprError(f"{path}: holds {index.ntotal} vectors of {index.d}-D, the map needs {count} of {dim}-D")
    if hasattr(index, "nprobe"):
        index.nprobe = nprobe
    if hasattr(index, "hnsw"):
        index.hnsw.efSearch = ef_search
    return index


def check_index_record(saved: SavedMap, record: dict[str, Any], path: Path) -> None:
    """The index is the one ``map.json`` records (its digest) and was built over this map's rows (their identity);
    an index recorded before identities is taken on its shape alone."""
    owner = str(Path(saved.folder) / INFO_FILE)
    if "digest" not in record:
        return
    if record.get("map") != saved.info.identity:
        raise SeqvprError(f"{path}: built over other rows than this map's (map.json's index names another map); "
                          f"rebuild it with seqvpr map index {saved.folder}")
    check_digest(path, record["digest"], owner)
    if record.get("rows_file"):
        check_digest(Path(saved.folder) / record["rows_file"], record["rows_digest"], owner)


def _seqnet(folder: str | Path):
    """The SeqNet module of a model folder (another kind is a one-line error)."""
    from seqvpr.models.registry import load_trained_model

    model = load_trained_model(folder)
    if model.kind != "seqnet":
        raise SettingError(f"{{models}} {folder} is a {model.kind} model; an index over seqnet windows needs a SeqNet")
    return model.module


def indexed_rows(saved: SavedMap) -> np.ndarray:
    """The map row of each vector of an index over windows (``index_rows.npy``)."""
    path = Path(saved.folder) / ROWS_FILE
    if not path.is_file():
        raise SeqvprError(f"{path}: missing map file (map.json names an index over windows)")
    try:
        return load_npy(path)
    except SeqvprError:
        raise
    except (ValueError, OSError, EOFError) as error:
        raise SeqvprError(f"{path}: unreadable or truncated ({str(error).splitlines()[0]})") from None


def window_search(saved: SavedMap, index, frames, segments: np.ndarray, k: int):
    """The ``k`` nearest map windows of each query window, by the index's own sequence descriptor: map rows and
    Euclidean distances [n_query, k] (-1 / +inf for queries without a window)."""
    method, length = saved.info.index["over"].split(":")
    described = window_vectors(frames, segments, int(length), method, index_model(saved))
    rows = np.full((described.n_frames, k), -1, dtype=np.int64)
    distances = np.full((described.n_frames, k), np.inf)
    found, found_distances = search_frames(index, described.vectors, k)
    mapped = indexed_rows(saved)
    rows[described.rows] = np.where(found >= 0, mapped[np.maximum(found, 0)], -1)
    distances[described.rows] = np.where(found >= 0, found_distances, np.inf)
    return rows, distances


def search_frames(index, frames: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest map frames of each row of ``frames`` [n, D]: rows [n, k] (-1 where none), distances. An
    HNSW search looks at ``k`` candidates at least (its efSearch is raised to ``k``)."""
    if hasattr(index, "hnsw") and index.hnsw.efSearch < k:
        index.hnsw.efSearch = k
    squared, rows = index.search(np.ascontiguousarray(frames, dtype=np.float32), k)
    return rows.astype(np.int64), np.sqrt(np.maximum(squared.astype(np.float64), 0.0))



REFINE = 10  # a PQ index over frames is searched this many times wider, then re-ranked on the map's own rows
REFINE_QUERIES = 64  # query frames re-ranked at a time ([64, S x REFINE, D] gathered rows at most)


def refined(descriptors, frames: np.ndarray, found: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``width`` nearest of each query frame's candidate map rows ``found`` [n, W] (-1: none) by exact Euclidean
    distance to the map's own rows (what a PQ index's codes only approximate): rows [n, width], distances."""
    from seqvpr.sequences.topk import best_of

    rows = np.full((len(found), width), -1, np.int64)
    distances = np.full((len(found), width), np.inf)
    for lo in range(0, len(found), REFINE_QUERIES):
        part = found[lo : lo + REFINE_QUERIES]
        wanted = np.unique(part[part >= 0])
        if not len(wanted):
            continue
        gathered = np.asarray(descriptors[wanted], dtype=np.float32)
        at = np.searchsorted(wanted, np.maximum(part, 0))
        exact = np.linalg.norm(gathered[at] - np.asarray(frames[lo : lo + REFINE_QUERIES], np.float32)[:, None], axis=2)
        exact = np.where(part >= 0, exact.astype(np.float64), np.inf)
        rows[lo : lo + len(part)], distances[lo : lo + len(part)] = best_of(part, exact, width)
    return rows, distances


class IndexNeighbors:
    """A saved map's faiss index as a shortlist's ``seqvpr.matchers.shortlisted.Neighbours``: the nearest map
    frames of query frames (an index over frames), or of query windows by the index's own sequence descriptor. A PQ
    index over frames is searched ``REFINE`` times wider and its candidates re-ranked on the map's rows."""

    def __init__(self, saved: SavedMap, nprobe: int = DEFAULT_NPROBE) -> None:
        self.saved, self.index = saved, open_frame_index(saved, nprobe)
        self.over, self.vectors = saved.info.index["over"], int(self.index.ntotal)
        self.refine = REFINE if parse_index_spec(saved.info.index["spec"]).pq and self.over == "frames" else 1

    def search(self, rows, segments: np.ndarray, width: int):
        from seqvpr.results import TopK

        if self.over == "frames":
            frames = np.asarray(rows)
            found, distances = search_frames(self.index, frames, min(width * self.refine, self.vectors))
            if self.refine > 1:
                found, distances = refined(self.saved.descriptors, frames, found, width)
        else:  # each query window's sequence descriptor finds its candidate frames directly
            found, distances = window_search(self.saved, self.index, rows, segments, width)
        return TopK(found, distances, found[:, 0] >= 0)
