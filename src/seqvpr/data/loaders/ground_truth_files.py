"""Ground truth read from files: a MATLAB GT struct (GThard/GTsoft) or VPR-Bench ``ground_truth_new.npy``.

Both give positives over the source frame indices of the two traversals; ``GroundTruth.restrict`` maps them to
the rows of (possibly sliced) traversals.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp

from seqvpr.arrays import PICKLE_REFUSAL, check_regular_file, load_mat, load_npy, open_npz
from seqvpr.data.ground_truth import GroundTruth
from seqvpr.errors import SeqvprError, SettingError, reading


def load_ground_truth_file(
    path: str | Path, n_query: int | None = None, n_reference: int | None = None, layout: str | None = None,
) -> GroundTruth:
    """Read a GT file into a [n_query, n_reference] sparse ground truth over source frame indices (a dense matrix is
    oriented by ``layout`` or by the traversal sizes ``n_query``/``n_reference``)."""
    path = Path(path)
    if not path.exists():
        raise SeqvprError(f"{path}: ground-truth file not found")
    check_regular_file(path, "a ground-truth file")
    with reading(path, "a ground-truth file"):
        return _load_ground_truth_file(path, n_query, n_reference, layout)


def _load_ground_truth_file(path: Path, n_query: int | None, n_reference: int | None, layout: str | None
                            ) -> GroundTruth:
    if path.suffix.lower() == ".mat":
        return _load_gt_mat(path)
    if path.suffix.lower() in (".npy", ".npz"):
        dense = _dense_matrix(path)
        if dense is not None:
            return _oriented(dense, path, n_query, n_reference, layout)
        if path.suffix.lower() == ".npy":
            return _load_vprbench_npy(path, n_query, n_reference)
    raise SeqvprError(f"{path}: unknown ground-truth format (expected a GT .mat, a VPR-Bench .npy or a dense "
                      "boolean matrix .npy/.npz)")


def _dense_matrix(path: Path) -> np.ndarray | None:
    """A 2-D boolean or 0/1 matrix stored in the file (an .npz: its one array, or ``gt``), else None (an object
    array .npy: VPR-Bench's rows, read by ``_load_vprbench_npy``)."""
    try:
        if path.suffix.lower() == ".npz":
            with open_npz(path) as archive:
                names = archive.files
                if not names:
                    raise SeqvprError(f"{path}: an empty .npz")
                if "gt" not in names and len(names) > 1:
                    raise SeqvprError(f"{path}: holds {', '.join(names)}; name the ground-truth array 'gt'")
                value = archive["gt" if "gt" in names else names[0]]
        else:
            value = load_npy(path)
    except SeqvprError as error:
        if path.suffix.lower() == ".npy" and str(error).endswith(PICKLE_REFUSAL):
            return None
        raise
    except (ValueError, OSError, EOFError) as error:
        raise SeqvprError(f"{path}: not a readable NumPy file ({type(error).__name__})") from None
    if value.ndim != 2:
        if path.suffix.lower() == ".npz":
            raise SeqvprError(f"{path}: expected a 2-D boolean matrix, got {value.dtype} {value.shape}")
        return None
    if value.dtype != bool and not np.isin(value, (0, 1)).all():
        raise SeqvprError(f"{path}: a dense ground truth holds booleans or 0/1, found other values")
    return value.astype(bool)


def _oriented(matrix: np.ndarray, path: Path, n_query: int | None, n_reference: int | None,
              layout: str | None) -> GroundTruth:
    """The dense matrix as [n_query, n_reference]: as ``layout`` says (``ref-query``: the Brisbane event set's and
    VPR-Bench's [n_reference, n_query]), else as the traversal sizes decide; a square one needs ``layout``."""
    if layout not in (None, "ref-query", "query-ref"):
        raise SettingError(f"{{layout}} must be ref-query or query-ref, got {layout!r}")
    if layout is None:
        if n_query is None or n_reference is None:
            raise SettingError(f"{path}: a dense ground truth needs the traversal sizes or {{layout}}")
        layout = _layout_from_sizes(matrix.shape, n_query, n_reference, path)
    hard = matrix.T if layout == "ref-query" else matrix
    return GroundTruth(sp.csr_array(hard), description=f"dense ground truth ({layout}) from {path.name}")


def _load_gt_mat(path: Path) -> GroundTruth:
    """``GT.GThard`` (and optional ``GT.GTsoft``), stored [n_reference, n_query] as in VPR_Tutorial."""
    contents = load_mat(path)
    if "GT" not in contents:
        raise SeqvprError(f"{path}: no variable 'GT' (expected a struct with GThard and GTsoft)")
    gt = contents["GT"]
    names = gt.dtype.names or ()
    if "GThard" not in names:
        raise SeqvprError(f"{path}: field GT.GThard is missing")
    hard = _as_matrix(gt["GThard"][0, 0], path, "GT.GThard")
    soft = _as_matrix(gt["GTsoft"][0, 0], path, "GT.GTsoft") if "GTsoft" in names else None
    if soft is not None and soft.shape != hard.shape:
        raise SeqvprError(f"{path}: GT.GTsoft has shape {soft.shape} but GT.GThard has {hard.shape}")
    return GroundTruth(hard, soft, description=f"GThard from {path.name}")


def _as_matrix(value, path: Path, field: str) -> sp.csr_array:
    """A [n_reference, n_query] 0/1 matrix transposed to our [n_query, n_reference] layout."""
    values = value.data if sp.issparse(value) else np.asarray(value)
    if values.dtype.kind not in "biuf" or (values.dtype.kind == "f" and not np.isfinite(values).all()):
        raise SeqvprError(f"{path}: {field} must hold 0/1 (or booleans), found {values.dtype} with NaN, inf or text")
    matrix = sp.csr_array(value) if sp.issparse(value) else sp.csr_array(values != 0)
    if matrix.ndim != 2:
        raise SeqvprError(f"{path}: {field} must be a 2-D matrix")
    return sp.csr_array(matrix.T.astype(bool))


def _load_vprbench_npy(path: Path, n_query: int | None, n_reference: int | None) -> GroundTruth:
    """Object array of rows [query_index, [reference indices]] (VPR-Bench), read without unpickling."""
    from seqvpr.data.loaders.vprbench import read_object_rows

    rows = read_object_rows(path)
    pairs = [(query, int(r)) for query, refs in rows for r in refs]
    q_idx = np.array([p[0] for p in pairs], dtype=np.int64)
    r_idx = np.array([p[1] for p in pairs], dtype=np.int64)
    if (q_idx < 0).any() or (r_idx < 0).any():
        raise SeqvprError(f"{path}: negative frame index")
    n_q = max(n_query or 0, len(rows), int(q_idx.max(initial=-1)) + 1)
    n_r = max(n_reference or 0, int(r_idx.max(initial=-1)) + 1)
    matrix = sp.csr_array((np.ones(len(pairs), dtype=bool), (q_idx, r_idx)), shape=(n_q, n_r))
    return GroundTruth(matrix, description=f"VPR-Bench ground truth from {path.name}")


def _layout_from_sizes(shape: tuple[int, int], n_query: int, n_reference: int, path: Path) -> str:
    """``ref-query`` or ``query-ref``: the one orientation whose sizes are the traversals' exactly, else the one
    that covers them (a cut of the traversals); both or neither is a one-line error."""
    for covers in (lambda a, b: a == b, lambda a, b: a >= b):
        rq = covers(shape[0], n_reference) and covers(shape[1], n_query)
        qr = covers(shape[0], n_query) and covers(shape[1], n_reference)
        if rq != qr:
            return "ref-query" if rq else "query-ref"
        if rq and qr:
            raise SettingError(f"{path}: a {shape[0]} x {shape[1]} matrix fits {n_reference} reference and {n_query} "
                              "query frames both ways: give {layout} ref-query or query-ref")
    raise SeqvprError(f"{path}: a {shape[0]} x {shape[1]} matrix fits neither {n_reference} reference x {n_query} "
                      "query frames nor the reverse")
