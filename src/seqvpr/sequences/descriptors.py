"""Sequence descriptors: one vector per frame window, for retrieval with a plain nearest-neighbour index.

Each frame that has a window (``windows.window_starts``: the spec's alignment and boundary rule, never across a
segment break) gets one vector summarising its L frames. Fixed poolings: smoothing (temporal mean), Delta
Descriptors (a fixed signed temporal filter) and concatenation. Learnable poolings: SeqNet (temporal Conv1d +
mean, "S_L"; S1 is its L = w = 1 case) and JIST's SeqGeM (a generalised mean over time with one learnable p).
Every descriptor is L2-normalised, so Euclidean distances between them are comparable across methods.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.sequences.windows import SequenceSpec, require_windows, window_frames, window_starts

SEQGEM_MODES = ("clamp", "signed")


def window_stack(
    descriptors: torch.Tensor, segment_ids: np.ndarray | None, spec: SequenceSpec
) -> tuple[torch.Tensor, np.ndarray]:
    """Frame windows [n_windows, L, D] for the frames that have one (spec's alignment and boundary rule), and
    those frames' rows."""
    starts, rows = _window_starts(len(descriptors), segment_ids, spec)
    frames = torch.as_tensor(window_frames(starts[rows], spec.length), device=descriptors.device)
    return descriptors[frames.reshape(-1)].reshape(len(rows), spec.length, -1), rows


def _window_starts(n_frames: int, segment_ids: np.ndarray | None, spec: SequenceSpec) -> tuple[np.ndarray, np.ndarray]:
    """Window start of every frame (-1 where none) and the rows of the frames that have one (velocity 1 only)."""
    if tuple(spec.velocities) != (1.0,):
        raise SeqvprError(f"sequence descriptors use velocity 1 only, got velocities {spec.velocities}")
    segments = np.zeros(n_frames, np.int64) if segment_ids is None else np.asarray(segment_ids)
    if segments.shape != (n_frames,):
        raise SeqvprError(f"segment_ids has shape {segments.shape} but there are {n_frames} frames")
    starts = window_starts(segments, spec.length, spec.offset, spec.boundary)
    require_windows(starts, spec.length, "sequence descriptors", segments)
    return starts, np.flatnonzero(starts >= 0)


def smoothing(windows: torch.Tensor) -> torch.Tensor:
    """Mean of the L frames, then L2 (seqNet's "smooth" baseline)."""
    return F.normalize(windows.mean(dim=1), dim=-1)


def delta_weights(length: int, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """Delta Descriptors' temporal weights as the reference: every w_t = 1/(L/2), the first L//2 negated.

    For odd L the weights do not sum to zero (L=5: -0.4, -0.4, +0.4, +0.4, +0.4): the later half has one frame
    more, so a static scene keeps a 2/L share of its frame descriptor instead of cancelling out.
    """
    weights = torch.full((length,), 1.0 / (length / 2), dtype=dtype, device=device)
    weights[: length // 2] *= -1
    return weights


def delta(windows: torch.Tensor) -> torch.Tensor:
    """Delta Descriptors: the reference's signed temporal filter X^T w (see ``delta_weights``), then L2."""
    weights = delta_weights(windows.shape[1], windows.dtype, windows.device)
    return F.normalize(torch.einsum("bld,l->bd", windows, weights), dim=-1)


def concatenation(windows: torch.Tensor) -> torch.Tensor:
    """The L per-frame-L2-normalised frames side by side [n, L*D], then L2 (JIST's "concat" aggregation)."""
    return F.normalize(F.normalize(windows, dim=-1).flatten(1), dim=-1)


class SeqNet(nn.Module):
    """SeqNet S_L: a temporal Conv1d (kernel w, no padding, bias) over the window, mean of its L-w+1 outputs, L2.

    The same kernel serves any L >= w; S1 is ``SeqNet(in_dim, out_dim, w=1)`` on L = 1 windows (a linear map + L2).
    """

    def __init__(self, in_dim: int, out_dim: int, w: int = 3) -> None:
        super().__init__()
        if in_dim < 1 or out_dim < 1 or w < 1:
            raise SeqvprError(f"SeqNet needs positive in_dim, out_dim and w, got {in_dim}, {out_dim}, {w}")
        self.in_dim, self.out_dim, self.w = in_dim, out_dim, w
        self.conv = nn.Conv1d(in_dim, out_dim, kernel_size=w, bias=True)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        """[B, L, D] -> [B, out_dim]; the mean over conv outputs is taken first (the conv is linear, so equal)."""
        length, dim = windows.shape[1], windows.shape[2]
        if length < self.w:
            raise SeqvprError(f"seqnet: sequence length {length} is shorter than the temporal kernel width w={self.w}")
        if dim != self.in_dim:
            raise SeqvprError(f"seqnet: the model expects {self.in_dim}-D descriptors, these are {dim}-D")
        # column k of `shifted_means` is the mean of the frames at kernel tap k over all L-w+1 positions
        shifted_means = F.avg_pool1d(windows.transpose(1, 2), kernel_size=length - self.w + 1, stride=1)
        # a conv with one output position is a linear map; as a matrix product it is exact float32 on CUDA too
        # (cuDNN convolutions default to TF32 there, which re-orders near neighbours against the CPU)
        out = F.linear(shifted_means.flatten(1), self.conv.weight.flatten(1), self.conv.bias)
        return F.normalize(out, dim=-1)


class SeqGeM(nn.Module):
    """JIST's SeqGeM: per dimension g_d = (mean_t max(x_td, eps)^p)^(1/p) with ONE learnable scalar p, then L2.

    ``mode="clamp"`` is the reference: negative entries become eps, so their sign (and size) is lost; that
    discards half the information of zero-centred descriptors such as PCA-whitened ones. ``mode="signed"`` is
    split-sign GeM: the same GeM over the positive parts max(x, 0) and over the negative parts max(-x, 0),
    concatenated to 2D dimensions ``[g(x+), g(x-)]``. Each half is an ordinary GeM of non-negative inputs (same
    eps clamp, same p, smooth gradients), no sign is lost, p = 1 gives g(x+) - g(x-) = mean_t x (up to eps),
    and large p tends to the per-dimension max and -min. The reference applies no L2 after pooling; we do unless
    ``normalize=False`` (what an imported JIST checkpoint uses, to rank exactly as upstream).
    """

    def __init__(self, p: float = 3.0, eps: float = 1e-6, mode: str = "clamp", normalize: bool = True) -> None:
        super().__init__()
        if mode not in SEQGEM_MODES:
            raise SeqvprError(f"SeqGeM mode must be one of {', '.join(SEQGEM_MODES)}, got {mode!r}")
        self.p = nn.Parameter(torch.tensor([float(p)]))
        self.eps, self.mode, self.normalize = eps, mode, normalize

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        """[B, L, D] -> [B, D] (clamp) or [B, 2D] (signed)."""
        pooled = self._gem(windows) if self.mode == "clamp" else torch.cat([self._gem(windows), self._gem(-windows)], -1)
        return F.normalize(pooled, dim=-1) if self.normalize else pooled

    def _gem(self, windows: torch.Tensor) -> torch.Tensor:
        """Generalised mean over time of max(x, eps) with the shared exponent p."""
        p = self.p.to(windows.dtype)
        return windows.clamp(min=self.eps).pow(p).mean(dim=1).pow(1.0 / p)


@dataclass(frozen=True)
class SequenceDescriptors:
    """One vector per frame that has a window: vectors [n_windows, D'] float32, rows (frame rows they belong
    to), n_frames."""

    vectors: np.ndarray
    rows: np.ndarray
    n_frames: int

    def __post_init__(self) -> None:
        if self.vectors.ndim != 2 or len(self.vectors) != len(self.rows):
            raise SeqvprError(
                f"sequence descriptors need vectors [n_windows, D] and one row per vector, got {self.vectors.shape} "
                f"and {len(self.rows)} rows"
            )
        if len(self.rows) and (self.rows.min() < 0 or self.rows.max() >= self.n_frames):
            raise SeqvprError(f"sequence descriptor rows must lie in [0, {self.n_frames})")

    @property
    def has_window(self) -> np.ndarray:
        """Bool [n_frames]: the frame has a sequence descriptor."""
        mask = np.zeros(self.n_frames, dtype=bool)
        mask[self.rows] = True
        return mask

    @property
    def dim(self) -> int:
        return int(self.vectors.shape[1])


#: poolings without parameters: windows [B, L, D] -> one vector per window; a new one is an entry here
FIXED_POOLINGS = {"smoothing": smoothing, "delta": delta, "concat": concatenation}


def sequence_descriptors(
    descriptors: np.ndarray | torch.Tensor,
    segment_ids: np.ndarray | None,
    spec: SequenceSpec,
    method: str,
    model: nn.Module | None = None,
    *,
    batch_size: int = 4096,
    device: str = "cpu",
) -> SequenceDescriptors:
    """Sequence descriptors of every frame with a window, computed in batches of windows without gradients.

    Frames are L2-normalised first (as the matching kernel does). ``seqnet`` needs its model; ``seqgem`` uses
    ``model`` or a fresh ``SeqGeM()``; the fixed methods take none.
    """
    source = _check_frames(descriptors)
    pool = _pooling(method, model, spec, source.shape[1])
    starts, rows = _window_starts(len(source), segment_ids, spec)
    starts = starts[rows]
    if isinstance(pool, nn.Module):
        pool, was_training = pool.to(device), pool.training
        pool.eval()
    vectors: np.ndarray | None = None
    try:
        with torch.no_grad():
            for begin in range(0, len(rows), batch_size):
                frames = window_frames(starts[begin : begin + batch_size], spec.length)
                windows = _normalized_windows(source, frames, device)
                out = pool(windows).float().cpu().numpy()
                if vectors is None:
                    vectors = np.empty((len(rows), out.shape[1]), dtype=np.float32)
                vectors[begin : begin + len(out)] = out
    finally:
        if isinstance(pool, nn.Module):
            pool.train(was_training)
    assert vectors is not None
    return SequenceDescriptors(vectors, rows.astype(np.int64), len(source))


def _pooling(method: str, model: nn.Module | None, spec: SequenceSpec, dim: int):
    """The pooling callable of ``method``, checking that a model is given exactly where one is needed and fits."""
    known = (*FIXED_POOLINGS, "seqnet", "seqgem")
    if method not in known:
        raise SeqvprError(f"sequence method {method!r} is not known (choose from: {', '.join(known)})")
    if method in FIXED_POOLINGS:
        if model is not None:
            raise SeqvprError(f"sequence method {method!r} takes no model")
        return FIXED_POOLINGS[method]
    if method == "seqgem":
        return SeqGeM() if model is None else model
    if model is None:
        raise SeqvprError("sequence method 'seqnet' needs a model (a SeqNet)")
    in_dim, w = getattr(model, "in_dim", dim), getattr(model, "w", 1)
    if in_dim != dim:
        raise SeqvprError(f"seqnet: the model expects {in_dim}-D descriptors, these are {dim}-D")
    if spec.length < w:
        raise SeqvprError(f"seqnet: sequence length {spec.length} is shorter than the temporal kernel width w={w}")
    return model


def _check_frames(descriptors: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """The frame descriptors as given (no copy), after checking they are a non-empty 2-D array."""
    source = descriptors if torch.is_tensor(descriptors) else np.asarray(descriptors)
    if source.ndim != 2 or len(source) == 0 or source.shape[1] == 0:
        raise SeqvprError(f"descriptors must be a non-empty [N, D] array, got shape {tuple(source.shape)}")
    return source


def _normalized_windows(source: np.ndarray | torch.Tensor, frames: np.ndarray, device: str) -> torch.Tensor:
    """Windows [n, L, D] of L2-normalised frames as float32 on ``device``; each covered frame is read, checked
    (failing on the first that is not finite) and normalised once, however many windows share it."""
    covered, position = np.unique(frames, return_inverse=True)
    block = _rows(source, covered).to(device=device, dtype=torch.float32)
    finite = torch.isfinite(block.sum(dim=1, dtype=torch.float64))  # finite only if every entry is
    if not bool(finite.all()):
        bad = int(covered[int(torch.nonzero(~finite)[0, 0])])
        raise SeqvprError(f"descriptors: frame row {bad} is not finite (NaN or inf)")
    block = F.normalize(block, dim=1)
    picked = block.index_select(0, torch.as_tensor(position.reshape(-1), device=block.device))
    return picked.reshape(*frames.shape, -1)


def _rows(source: np.ndarray | torch.Tensor, rows: np.ndarray) -> torch.Tensor:
    """Rows of a tensor or array as a tensor, without copying the whole source."""
    if torch.is_tensor(source):
        return source.index_select(0, torch.as_tensor(rows, device=source.device))
    if source.flags.c_contiguous and source.flags.writeable and source.dtype.isnative:
        return torch.from_numpy(source).index_select(0, torch.as_tensor(rows))  # fast path, no copy of source
    return torch.from_numpy(np.ascontiguousarray(source[rows]))
