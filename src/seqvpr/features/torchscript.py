"""A user's own frame encoder (MegaLoc, SALAD, BoQ, DINOv2...), exported on their machine as TorchScript
(``torch.jit.script`` / ``trace`` + ``save``) or ``torch.export`` (``.pt2``) and run here without its source code.

The encoder takes a [B, 3, H, W] batch normalised with a mean and std and returns [B, D] descriptors, used as they
come out (no L2-normalisation here: matching normalises unless told not to).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import nn

from seqvpr.errors import SeqvprError

#: what a failing encoder may raise: TorchScript interpreter errors, torch.export guards, shape and type errors
_ENCODER_ERRORS = (RuntimeError, AssertionError, ValueError, TypeError, IndexError)


class TorchScriptEncoder(nn.Module):
    """A loaded encoder behind the input normalisation it expects; images in [0, 1] -> [B, D] descriptors.

    The batch reaches the encoder contiguous (not channels-last), as it was most likely exported. The encoder keeps
    the mode it was loaded in (eval): an exported program cannot switch modes, so ``train``/``eval`` do not reach it.
    """

    def __init__(self, module: nn.Module, mean: Sequence[float], std: Sequence[float], source: Path) -> None:
        super().__init__()
        self.module, self.source = module, str(source)
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))

    def train(self, mode: bool = True) -> TorchScriptEncoder:
        self.training = mode
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        batch = ((images - self.mean) / self.std).contiguous()
        try:
            out = self.module(batch)
        except _ENCODER_ERRORS as error:
            raise SeqvprError(
                f"{self.source}: the encoder failed on a batch of shape {list(batch.shape)} ({_last_line(error)}); "
                "check --image-size and the batch sizes the export accepts"
            ) from None
        return _checked_descriptors(out, len(batch), self.source)


def _checked_descriptors(out: object, batch: int, source: str) -> torch.Tensor:
    """The encoder's output as float32 [B, D], or a one-line error saying what it returned instead."""
    if not isinstance(out, torch.Tensor):
        raise SeqvprError(f"{source}: the encoder returned a {type(out).__name__}, expected a [batch, dim] tensor")
    if out.dim() != 2 or out.shape[0] != batch:
        raise SeqvprError(
            f"{source}: the encoder returned shape {list(out.shape)} for {batch} images, expected [batch, dim] "
            "descriptors (pool and flatten inside the exported model)"
        )
    return out.float()


def load_encoder(path: str | Path, mean: Sequence[float], std: Sequence[float]) -> TorchScriptEncoder:
    """The TorchScript or ``torch.export`` file at ``path`` (loaded on the CPU) behind ``mean``/``std`` input
    normalisation; a missing or unloadable file is a one-line error naming it."""
    path = Path(path)
    if not path.is_file():
        raise SeqvprError(f"{path}: no such model file (expected a TorchScript or torch.export .pt2 file)")
    return TorchScriptEncoder(_load_module(path), mean, std, path)


def _load_module(path: Path) -> nn.Module:
    """The module in a TorchScript or torch.export file, whichever it is (``.pt2`` tried as torch.export first);
    the reason the likelier format failed, in one line, if neither loads."""
    loaders = (_load_exported, _load_scripted) if path.suffix == ".pt2" else (_load_scripted, _load_exported)
    failures = []
    for loader in loaders:
        try:
            return loader(path)
        except Exception as error:  # noqa: BLE001 - a user's file can fail to load in many ways; both loaders are tried
            failures.append(_last_line(error).split(". ")[0])
    raise SeqvprError(
        f"{path}: not a TorchScript or torch.export file ({failures[0]}); export the model with "
        "torch.jit.script/trace + save or torch.export.save (a state dict or pickled model is not enough)"
    )


def _load_scripted(path: Path) -> nn.Module:
    """A TorchScript archive, in eval mode (torch's deprecation notice for TorchScript is not the user's to act on
    here: the file is what they have)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "`torch.jit", DeprecationWarning)
        return torch.jit.load(str(path), map_location="cpu").eval()


def _load_exported(path: Path) -> nn.Module:
    """A ``torch.export`` program as a callable module (its train/eval mode is fixed at export). torch.export logs
    why a file failed (with a traceback) and raises a vaguer error; the logged reason is raised instead. Its pickled
    parts are read weights-only: torch.export would otherwise retry them with full unpickling (code in the file)."""
    with _captured_errors("torch.export") as logged, _weights_only_loads():
        try:
            return torch.export.load(str(path)).module()
        except Exception as error:  # noqa: BLE001 - re-raised, with the logged reason where there is one
            raise (logged[-1] if logged else error) from None


@contextmanager
def _weights_only_loads() -> Iterator[None]:
    """Every ``torch.load`` inside runs weights-only, whatever its caller asks (torch's own switch, read per call),
    so no library code reached from here can unpickle a file; the previous setting is restored."""
    import os

    key = "TORCH_FORCE_WEIGHTS_ONLY_LOAD"
    previous = os.environ.get(key)
    os.environ[key] = "1"
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = previous


class _ErrorList(logging.Handler):
    """A log handler that keeps the exceptions of the records it gets and prints nothing."""

    def __init__(self) -> None:
        super().__init__()
        self.errors: list[BaseException] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info and record.exc_info[1] is not None:
            self.errors.append(record.exc_info[1])


@contextmanager
def _captured_errors(logger: str) -> Iterator[list[BaseException]]:
    """The exceptions a library's logger reports during the block, listed instead of printed."""
    handler, log = _ErrorList(), logging.getLogger(logger)
    handlers, propagate = log.handlers, log.propagate
    log.handlers, log.propagate = [handler], False
    try:
        yield handler.errors
    finally:
        log.handlers, log.propagate = handlers, propagate


def _last_line(error: BaseException) -> str:
    """The informative line of an error (TorchScript's own message comes last, after its traceback)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__
