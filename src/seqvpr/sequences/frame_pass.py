"""A query's frames one at a time (a localiser's): a frame's prepared row in a buffer reused frame after frame, and
a reference prepared for one-frame distance passes. Each step here runs right after a pass over the whole map has
flushed the caches, where every Python-level operation costs tens of microseconds: views are made once, and the
arithmetic runs in compiled passes that give the matching kernel's values bit for bit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqvpr import sequences
from seqvpr.sequences.matching import EPS32, TINY32, ReferenceRows, reference_rows, reference_squared_norms

TINY_F32 = np.float32(TINY32)


@dataclass(frozen=True)
class FrameRow:
    """One query frame's prepared row (float32, CPU) and its views, made once: ``row`` [1, D] (what a distance
    pass's matrix product takes), ``vector`` [D] and ``numbers`` [D] (numpy, what compiled passes take). A
    localiser reuses one buffer frame after frame (each view costs microseconds once the map's pass has flushed
    the caches); a stepper copies what it keeps."""

    row: torch.Tensor
    vector: torch.Tensor
    numbers: np.ndarray

    @classmethod
    def empty(cls, dim: int) -> FrameRow:
        numbers = np.zeros((1, dim), dtype=np.float32)
        row = torch.from_numpy(numbers)
        return cls(row, row[0], numbers[0])

    @classmethod
    def of(cls, values) -> FrameRow:
        """A fresh row holding ``values`` [D] (a tensor or array), as float32."""
        numbers = np.asarray(values.detach().cpu() if torch.is_tensor(values) else values, dtype=np.float32)
        row = cls.empty(len(numbers))
        row.numbers[:] = numbers
        return row

    def set_unit(self, numbers: np.ndarray) -> FrameRow:
        """Hold ``unit_rows`` of ``numbers`` [D] (float32), bit for bit: the largest magnitude and both float32
        divisions in compiled passes, the norm torch's own reduction (the same float32 sum)."""
        kernels = sequences._fused
        kernels.scale_by_peak_(numbers, self.numbers, TINY_F32)
        kernels.divide_(self.numbers, np.float32(max(float(torch.linalg.vector_norm(self.vector)), EPS32)))
        return self

    def finite(self) -> bool:
        """Whether the row holds no NaN or infinite value (a non-finite descriptor stays so through
        ``set_unit``)."""
        return sequences._fused.all_finite(self.numbers)


class ReferenceBlocks:
    """A reference prepared for one-frame distance passes (a localiser's): its rows' squared norms (float32, as the
    pass uses them) and, where the rows are float32 on the CPU (in memory, or a map's memory map), torch views of
    its blocks of ``columns`` rows made once; coded rows are read and decoded a block at a time each pass."""

    def __init__(self, reference: ReferenceRows, columns: int = 65536) -> None:
        self.reference, self.columns = reference, columns
        self.norms = reference_squared_norms(reference, columns)
        bounds = [(lo, min(lo + columns, len(reference))) for lo in range(0, len(reference), columns)]
        like = torch.empty(0)
        plain = isinstance(reference, np.ndarray) and reference.dtype == np.float32 and reference.flags.writeable
        self.blocks = [(lo, hi, reference_rows(reference, slice(lo, hi), like).T if plain else None)
                       for lo, hi in bounds]  # each block's rows transposed: what mm takes

    def __len__(self) -> int:
        return len(self.reference)

    def dots_into(self, query: torch.Tensor, out: torch.Tensor) -> None:
        """One frame's dot products with every row (``query`` [1, D], float32, CPU) written into ``out`` [1, N],
        block by block in the calling thread's pools alone."""
        whole = len(self.blocks) == 1
        for lo, hi, columns in self.blocks:
            columns = columns if columns is not None else reference_rows(self.reference, slice(lo, hi), query).T
            torch.mm(query, columns, out=out if whole else out[:, lo:hi])

    def distances_into(self, frame: FrameRow, out: np.ndarray) -> np.ndarray:
        """One frame's distances [N] (float32, CPU) to every row, written into ``out``: the values
        ``distances_to_reference`` gives."""
        self.dots_into(frame.row, torch.from_numpy(out)[None])
        sequences._fused.frame_distances_(out, frame.numbers, self.norms)
        return out
