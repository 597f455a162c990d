"""Any image encoder seqvpr runs, written as a file a robot's runtime reads: ONNX (ONNX Runtime, TensorRT...),
TorchScript or ``torch.export``. The encoder is a built-in backbone with its pooling head (its ImageNet or given
weights) or a trained model folder's frame encoder (JIST's, CosPlace's, the thumbnail CNN inside a JIST model); the
file takes float [batch, 3, height, width] RGB pixels in [0, 1] and returns [batch, dim] descriptors, its input
contract written in its metadata, and it is checked against torch on a probe batch before it replaces anything.

Same name as ``seqvpr.cli.export``: the command that calls this."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.features.engines import OnnxEncoder, export_onnx, input_contract, write_checked
from seqvpr.io import atomic_write, check_output_apart

FORMATS = ("onnx", "torchscript", "export")
SUFFIXES = {"onnx": (".onnx",), "torchscript": (".pt", ".pth", ".ts"), "export": (".pt2",)}


@dataclass(frozen=True)
class ExportedEncoder:
    """What was written: the file, its format, the input size it takes and its descriptor dimension."""

    path: Path
    format: str
    width: int
    height: int
    dim: int
    difference: float


def frame_encoder(source: str, image_size: tuple[int, int] | None = None, pooling: str = "gem",
                  weights: str | None = "imagenet") -> tuple[nn.Module, int, int, str]:
    """The encoder a source names, with its input size and a description: a built-in backbone's name (with
    ``pooling``, ``weights`` and ``image_size``, default 320x240) or a model folder whose model describes images
    (JIST's frame encoder, CosPlace's), at its own size unless ``image_size`` is given."""
    from seqvpr.features.extraction import BACKBONES, ExtractorConfig, build_extractor

    if source in BACKBONES:
        width, height = image_size or (320, 240)
        config = ExtractorConfig(source, weights, pooling, width, height)
        return build_extractor(config), width, height, f"{source} + {pooling}, weights {weights}"
    from seqvpr.models.registry import load_trained_model

    model = load_trained_model(source)
    if model.image_size is None:
        raise SeqvprError(f"{source}: a {model.kind} model does not describe images; export a JIST or CosPlace "
                          "model folder, or a backbone by name")
    width, height = image_size or model.image_size
    module = getattr(model.module, "encoder", model.module)
    return module.eval(), width, height, f"the frame encoder of {model.kind} model {source}"


def export_encoder(source: str, out: str | Path, format: str = "onnx", image_size: tuple[int, int] | None = None,
                   pooling: str = "gem", weights: str | None = "imagenet") -> ExportedEncoder:
    """Write ``source``'s frame encoder (``frame_encoder``) to ``out`` in ``format`` and check it against torch on a
    probe batch (within ``engines.TOLERANCE``); a file that differs is removed and the difference is one line."""
    checks.text(format, "format", FORMATS)
    out = checks.a_path(out, "out")
    if out.suffix.lower() not in SUFFIXES[format]:
        raise SettingError(f"{{out}} {out}: {format} files are named {' or '.join(SUFFIXES[format])} (so that no other "
                           "file is overwritten by mistake)")
    if image_size is not None and (isinstance(image_size, (str, bytes)) or len(image_size) != 2):
        raise SettingError(f"{{image_size}} must be (width, height), got {checks.shown(image_size)}")
    image_size = None if image_size is None else tuple(checks.whole(side, "image_size", 1) for side in image_size)
    checks.text(pooling, "pooling", ("gem",))
    if weights is not None:
        checks.text(weights, "weights")
    check_output_apart(out, [source if Path(source).exists() else None, weights if weights not in (None, "imagenet")
                             else None], "the exported file")
    module, width, height, what = frame_encoder(checks.text(source, "source"), image_size, pooling, weights)
    contract = {"seqvpr.source": what, **input_contract(width, height)}
    with torch.no_grad():
        dim = int(module(torch.zeros(1, 3, height, width)).shape[1])
    difference = write_checked(module, width, height, out,
                               lambda made: WRITERS[format](module, width, height, made, contract), READERS[format])
    return ExportedEncoder(out, format, width, height, dim, difference)


def _write_onnx(module: nn.Module, width: int, height: int, out: Path, contract: dict[str, str]) -> Path:
    return export_onnx(module, width, height, out, contract)


def _write_torchscript(module: nn.Module, width: int, height: int, out: Path, contract: dict[str, str]) -> Path:
    """A trace over a probe image (the batch size stays free: every operation is per image), contract inside."""
    import warnings

    probe = torch.rand(2, 3, height, width)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        traced = torch.jit.trace(module.to("cpu").eval(), probe)
    with atomic_write(out, "wb") as handle:
        torch.jit.save(traced, handle, _extra_files={"seqvpr.json": json.dumps(contract)})
    return out


def _write_export(module: nn.Module, width: int, height: int, out: Path, contract: dict[str, str]) -> Path:
    """A ``torch.export`` program with a dynamic batch (at least 1), contract inside."""
    batch = torch.export.Dim("batch", min=1, max=4096)
    program = torch.export.export(module.to("cpu").eval(), (torch.rand(2, 3, height, width),),
                                  dynamic_shapes=({0: batch},))
    with atomic_write(out, "wb") as handle:
        torch.export.save(program, handle, extra_files={"seqvpr.json": json.dumps(contract)})
    return out


def _read_back(path: Path):
    """A TorchScript or ``torch.export`` file as seqvpr reads a user's (no unpickling), pixels in [0, 1]."""
    from seqvpr.features.torchscript import load_encoder

    return load_encoder(path, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))


WRITERS = {"onnx": _write_onnx, "torchscript": _write_torchscript, "export": _write_export}
READERS = {"onnx": OnnxEncoder, "torchscript": _read_back, "export": _read_back}
